"""telemetry: LCM types (telemetry/*.lcm), their generated code, and the publishers.

- ``telemetry.lcmtypes.canon``: the generated Python types (status, drive_status, event, command,
  reply); ``telemetry.generate`` regenerates them, the Java sources and ``canon_types.jar``.
- ``telemetry.publisher``: channel names, ``open_lcm``, ``StatusPublisher``, ``EventPublisher``.
- ``telemetry.auth``: signed commands (HMAC key file, ``sign``, ``Verifier``, rate limits).
- ``telemetry.commands``: the command verbs, ``check_command``, ``CommandServer``.
- ``telemetry.url``: LCM URL parsing and whether traffic leaves the host.
- ``telemetry.config``: the ``[telemetry]`` table. See docs/telemetry.md.
"""
