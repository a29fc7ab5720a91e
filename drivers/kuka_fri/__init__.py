"""KUKA FRI (LBR iiwa on Sunrise): proto2 wire codec, joint commander and a fake controller.

``wire`` holds the proto2 primitives, ``messages`` the FRI messages (see ``PROTOCOL.md``),
``session`` the client's per-message logic, ``commander`` the ``FriCommander`` (its UDP port
and exchange thread) and ``fake`` the ``FakeSunrise`` controller twin.
"""
