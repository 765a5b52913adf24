"""The stage boards: the Marlin emulator (dialect, G-codes, planner) and a real stage firmware
under simavr, in lock-step with the simulation or free-running on a pty."""
