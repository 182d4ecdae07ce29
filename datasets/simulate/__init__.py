"""Flight simulator: ground truth for every sensor (see issue 3).

``simulate(scenario, seed, options) -> Flight`` flies a rigid-body multirotor with linear rotor drag
along one of ``SCENARIOS`` and synthesises IMU, AHRS attitude, yaw, tilted rangefinder, monocular
SLAM (unknown scale, latency, resets), downward optical flow (``flowdeck``, or
``SimOptions.flow_rate_hz``) and downward-camera images of a noise carpet;
``simulate_to_folder`` writes the flight in fgnav's native folder format.
"""

from .options import CRAZYFLIE_LIKE, SimOptions, SimulationError
from .scenarios import SCENARIOS
from .simulator import simulate, simulate_to_folder, world_T_cam_at

__all__ = [
    "CRAZYFLIE_LIKE",
    "SCENARIOS",
    "SimOptions",
    "SimulationError",
    "simulate",
    "simulate_to_folder",
    "world_T_cam_at",
]
