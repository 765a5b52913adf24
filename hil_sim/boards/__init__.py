"""The two emulated boards: the sensor (the real firmware core, PC build, or the ARM build in
QEMU) and the stage (Marlin's serial dialect and planner)."""

