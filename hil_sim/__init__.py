"""The dmdsm software-in-the-loop emulator: both boards on pseudo-terminals plus scene physics."""
