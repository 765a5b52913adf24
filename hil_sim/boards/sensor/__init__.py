"""The sensor boards, interchangeable behind one interface: the firmware core (PC build) fed by
the physics, the exact NUCLEO ELF on the rehosted H743, and the ARM build under QEMU."""
