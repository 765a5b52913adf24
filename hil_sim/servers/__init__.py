"""The emulator run as a whole: both boards and the scene stepped in simulated time, behind
pseudo-terminals, with fault injection on the links."""

