"""The MAVLink parameter protocol: PARAM_* messages over the runtime's parameter registry.

`protocol` answers lists, reads and sets (index order, refusals, announcements); `codec` owns
the 4 value bytes on the wire (bytewise or C-cast integers, never through a Python float).
The bridge's own MAV_* parameters are declared in `gcs_bridge.bridge_params`, not here.
"""
