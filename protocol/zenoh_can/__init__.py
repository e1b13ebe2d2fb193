"""CAN over Zenoh: a python-can interface (:class:`ZenohBus`) whose buses are clients of one
Zenoh router (``scara-router``). :mod:`.frame` is the frame format, :mod:`.config` the session
settings and topology, :mod:`.bus` the bus, :mod:`.router` the router command."""

from protocol.zenoh_can.bus import ZenohBus

__all__ = ["ZenohBus"]
