"""OptiTrack NatNet (Motive): wire codec, the ``NatNetSensor`` client and the ``FakeMotive`` twin.

``codec`` decodes/encodes every NatNet message (NatNet 3.0 – 4.1 layouts); ``client`` is the
``PositionSensor`` (registered as driver ``"natnet"``); ``fake`` is a Motive server on
loopback that streams frames from a ``drivers.sim.scene.MarkerScene``.
"""
