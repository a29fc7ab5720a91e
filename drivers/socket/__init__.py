"""The ``socket`` joint sensor: records joint angles with the ball held in a socket
(sensorless calibration, ``calib.fit.socket``). See ``drivers.socket.sensor``."""

from drivers.socket.sensor import SocketSensor

__all__ = ["SocketSensor"]
