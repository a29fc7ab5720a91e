"""KUKA FRI (LBR iiwa on Sunrise): proto2 wire codec, joint commander and a fake controller.

``wire`` holds the proto2 primitives, ``messages`` the FRI messages (see ``PROTOCOL.md``),
``commander`` the ``FriCommander`` client and ``fake`` the ``FakeSunrise`` controller twin.
"""
