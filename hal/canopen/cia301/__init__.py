"""CiA 301, the CANopen application layer: what the backend and the simulated drives say on the bus.

One module per service, as the standard is laid out: :mod:`.nmt` (network management and the
heartbeat's states), :mod:`.sdo` (expedited SDO transfers and a client that never waits),
:mod:`.pdo` (mapping entries, the codec of a mapped PDO, the SDO writes that configure one),
:mod:`.emcy` (emergency messages, short ones included) and :mod:`.heartbeat` (the consumer's
watchdog). Everything here is plain data and arithmetic on frames: no bus, no thread, no clock
(times are passed in), so the tick can call it and the tests can check it byte by byte.
"""
