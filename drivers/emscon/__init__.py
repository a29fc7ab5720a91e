"""Leica emScon TPI driver: binary packets over TCP (port 700) to an emScon server (AT4xx/AT9xx).

- ``enums``: the ``ES_...`` enumerations of ``ES_C_API_Def.h`` (TPI 3.6).
- ``codec``: packet layouts, ``encode`` / ``decode`` / ``decode_request``, framing.
- ``status``: every ``ES_ResultStatus`` mapped to the driver errors of ``drivers.errors``.
- ``client``: ``EmsconSensor``, a ``PositionSensor`` with ``aim`` / ``search`` / ``status``, a
  façade over ``channel`` (``EmsconChannel``: TCP connection, command exchange, notifications),
  ``configuration`` (``TrackerConfiguration``: preparation on connect, status, air, reflector,
  probe), ``measuring`` (``StationaryMeasurer``) and ``steering`` (``BeamSteering``: aim, search).
- ``fake``: ``FakeEmscon`` server logic around the simulated tracker, served by ``EmsconServer``.
"""
