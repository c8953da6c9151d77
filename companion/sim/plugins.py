"""The simulator of a device that a row of the vehicle's table brings (`Row.simulator`).

The SITL world simulates the thesis aircraft's IMU, GPS and servo board itself: their timing
(the IMU's 100 Hz tick, the GPS's latency queue, the board answering each command at once) is
the world's. A device added later brings its own simulator as ``module:Class`` in its row, and
the world builds it with a generator of its own and calls it once per world tick with the
truth; what it returns is written to the device's port (a pseudo-terminal, or the in-process
port of a lockstep flight) exactly as a thesis device's bytes are, through the same byte faults.

Its generator is drawn after every thesis device's, so adding a device changes no other
sensor's draws, and a lockstep flight with it is as reproducible as one without.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from companion.core.lazy import load
from companion.vehicle import VEHICLE, VehicleTable

if TYPE_CHECKING:  # the table is read by every flight; JSBSim and numpy load with the world
    import numpy as np

    from companion.sim.truth import TruthState

__all__ = ["DeviceSimulator", "build_simulator", "simulated_devices"]


class DeviceSimulator(Protocol):
    """What the world asks of a device's simulator. Built as ``cls(rng)``."""

    def tick(self, t_s: float, truth: TruthState) -> bytes:
        """The bytes the device sends during the world tick that ends at `t_s` (simulated
        seconds since the start); empty when it sends nothing this tick."""
        ...


def build_simulator(spec: str, rng: np.random.Generator) -> DeviceSimulator:
    """The simulator that ``module:Class`` `spec` names, built on `rng`; a LookupError names a
    spec that does not load."""
    cls = load(spec)
    sim: DeviceSimulator = cls(rng)
    return sim


def simulated_devices(table: VehicleTable = VEHICLE) -> dict[str, str]:
    """Device name -> simulator spec, for every device row of `table` that names one, in
    table order: the devices a world builds beside the thesis aircraft's."""
    return {row.name: row.simulator for row in table.devices() if row.simulator}
