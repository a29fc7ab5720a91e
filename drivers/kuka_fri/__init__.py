"""KUKA FRI (LBR iiwa on Sunrise): proto2 wire codec, joint commander and a fake controller.

``wire`` holds the proto2 primitives, ``messages`` the FRI messages (see ``PROTOCOL.md``),
``session`` the client's per-message logic, ``commander`` the ``FriCommander`` (with ``link``,
its exchange process, and ``session_view``, the session as this process sees it) and ``fake``
the ``FakeSunrise`` controller twin (with ``fake_session``, ``fake_answers``, ``fake_sender``,
``fake_servo``, ``fake_windows``, ``fake_monitoring``, ``fake_port``).
"""
