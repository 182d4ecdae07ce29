"""fgnav.datasets: flight data model, readers/writers of log formats, and the flight simulator.

Knows nothing of GTSAM. Import as ``fgnav.datasets``.
"""

from .errors import FgnavError, FlightDataError, FlightFormatError
from .types import (
    AttitudeSeries,
    Calibration,
    CameraIntrinsics,
    Flight,
    ImageSeries,
    ImuNoise,
    ImuSeries,
    RangeSeries,
    SlamSeries,
    Trajectory,
    YawSeries,
)

__all__ = [
    "AttitudeSeries",
    "Calibration",
    "CameraIntrinsics",
    "FgnavError",
    "Flight",
    "FlightDataError",
    "FlightFormatError",
    "ImageSeries",
    "ImuNoise",
    "ImuSeries",
    "RangeSeries",
    "SlamSeries",
    "Trajectory",
    "YawSeries",
]
