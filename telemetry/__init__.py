"""telemetry: LCM types (telemetry/*.lcm), their generated code, and the publishers."""
