"""The link to a flight controller (ArduPilot, PX4): the source that fills the vehicle's slots
from the autopilot's MAVLink (`link`), its conversions (`samples`), its clock map (`timesync`)
and its stream requests (`streams`). docs/autopilot.md."""
