"""Transports: the serial and CAN ports a sheet is reached through, the SLCAN and isolated
udp_multicast python-can interfaces, and a serial port read by a process of its own."""
