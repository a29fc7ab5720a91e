"""Leica emScon TPI driver: binary packets over TCP (port 700) to an emScon server (AT4xx/AT9xx).

- ``codec``: packet layouts and enums of ``ES_C_API_Def.h`` (TPI 3.6), ``encode`` / ``decode``.
- ``status``: every ``ES_ResultStatus`` mapped to the driver errors of ``drivers.errors``.
- ``client``: ``EmsconSensor``, a ``PositionSensor`` with ``aim`` / ``search`` / ``status``.
- ``fake``: ``FakeEmscon`` server logic around the simulated tracker, served by ``EmsconServer``.
"""
