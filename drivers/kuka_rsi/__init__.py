"""KUKA RobotSensorInterface (RSI) over Ethernet: XML codec, joint commander, fake KR C4.

``codec`` holds the wire format, ``commander.RsiCommander`` the real-time answering thread and
safe motion, ``fake.FakeKrc4`` a controller twin that speaks the same protocol on loopback.
"""
