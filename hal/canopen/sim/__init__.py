"""Simulated CANopen SEA drives on a virtual bus, in front of the simulated plant."""
