"""OptiTrack NatNet (Motive): wire codec, the ``NatNetSensor`` client and the ``FakeMotive`` twin.

``codec`` decodes/encodes every NatNet message (NatNet 3.0 – 4.1 layouts; newer versions are
refused, never read with an older layout); ``client`` is the ``PositionSensor`` (registered as
driver ``"natnet"``): it follows how Motive announces it streams (multicast group and port, or
unicast) and selects rigid bodies, labeled markers, assets' markers by name and skeleton bones.
It composes: ``settings`` (options and the ``natnet://`` URL), ``command`` (command socket and
replies), ``handshake`` (connect()'s exchange), ``receiver`` (the thread reading datagrams),
``server_state`` (what Motive announced, re-announcements), ``newest_frame`` (frame ordering and
silence), ``transport`` (unicast or multicast), ``selection`` (marker selectors and their ids)
and ``samples`` (a frame as marker samples).
``fake`` is a Motive server on loopback (unicast or multicast, as Motive by default) that
streams frames from a ``drivers.sim.scene.MarkerScene`` as a rigid body, skeleton or trained
markerset.
"""
