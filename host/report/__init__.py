"""Reports: figures like the paper's, the demo report page, and the demo that runs the
pipeline on the emulator through the `dmdsm` command."""

