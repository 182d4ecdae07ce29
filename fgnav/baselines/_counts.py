"""Counts the SLAM-and-range filters share (reported in ``Estimate.info``, never silent)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class SlamRangeCounts:
    """What a filter with SLAM and range updates did with them.

    Attributes:
        slam_updates, slam_rejected_gate: SLAM poses used / rejected by the innovation gate.
        slam_waiting_reinit: SLAM poses of a new map held while its scale is re-initialised.
        session_resets: SLAM sessions (map resets) that restarted the alignment.
        range_updates, range_rejected_gate, range_rejected_tilt: range readings used / gated /
            rejected for the tilt of the beam.
        gating_resets: times every SLAM pose was gated for ``slam_reset_s`` and the vehicle
            state was re-initialised from the SLAM.
        extra: filter-specific counts.
    """

    slam_updates: int = 0
    slam_rejected_gate: int = 0
    slam_waiting_reinit: int = 0
    session_resets: int = 0
    range_updates: int = 0
    range_rejected_gate: int = 0
    range_rejected_tilt: int = 0
    gating_resets: int = 0
    extra: dict = field(default_factory=dict)

    def gated(self, stream: str, ok: bool) -> bool:
        """Count one update of ``stream`` (``"slam"``, ``"range"``, ...) as used
        (``<stream>_updates``) or rejected by the innovation gate (``<stream>_rejected_gate``);
        ``ok`` back."""
        name = f"{stream}_updates" if ok else f"{stream}_rejected_gate"
        setattr(self, name, getattr(self, name) + 1)
        return ok

    def unused(self) -> dict[str, int]:
        """The shared counts of measurements not used, as ``stream:reason -> count``
        (:mod:`fgnav.baselines._inputs`)."""
        return {
            "slam:gated": self.slam_rejected_gate,
            "slam:waiting-reinit": self.slam_waiting_reinit,
            "range:gated": self.range_rejected_gate,
            "range:tilted": self.range_rejected_tilt,
        }
