"""CiA 402, the drive profile: the power state machine (both sides of it) and the drive's units."""
