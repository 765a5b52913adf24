"""The demo: an application on top of the `dmdsm` commands, running the paper's experiments on
the emulator through the same commands and serial paths a user with hardware runs.

session.py (the emulator session; stages 1-3 and 5), household.py (stage 4), models.py
(stage 6: the campaign and its 3D models), run.py (all six,
then out/report.html, report.md, summary.json), command.py (`dmdsm demo`, which the console
entry point, host/entry.py, adds to the commands' parser).
"""
