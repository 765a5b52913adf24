"""The emulator's physics: scene geometry and ray cast, the objects on the turntable, and the
transducer waveforms of one laser shot."""

