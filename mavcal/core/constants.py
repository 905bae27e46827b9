"""Physical constants shared by every stage (defined once, here)."""

#: Standard gravity, m/s^2 (ArduPilot's GRAVITY_MSS; 1 g of the telemetry's milli-g units).
GRAVITY_MPS2 = 9.80665
