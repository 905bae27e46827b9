"""Guided capture: the session (state and pose advice), its status text, and the live loop.

* :mod:`mavcal.capture.session`: :class:`CaptureSession`, :class:`CaptureConfig`,
  :class:`CaptureStatus`, :class:`PoseAdvice` (no vehicle I/O);
* :mod:`mavcal.capture.poses`: the candidate poses, their words and what each would add;
* :mod:`mavcal.capture.screen`: :func:`status_line`, :func:`status_screen`;
* :mod:`mavcal.capture.live`: :func:`capture_live` on a MAVLink device (imported on first
  use of its names, so that the session does not pull in the MAVLink link layer).
"""
from mavcal.capture.poses import candidate_poses, describe_pose, euler_matrix, heading_gradients, pose_scores
from mavcal.capture.screen import status_line, status_screen
from mavcal.capture.session import (
    INITIAL_PLAN,
    PLAN_FIRST,
    CaptureConfig,
    CaptureSession,
    CaptureStatus,
    PoseAdvice,
    coverage_map,
)

_LIVE_NAMES = ("capture_live", "CaptureAbortedError", "LiveCaptureInfo")


def __getattr__(name: str) -> object:
    if name in _LIVE_NAMES:
        from mavcal.capture import live

        return getattr(live, name)
    raise AttributeError(f"module 'mavcal.capture' has no attribute {name!r}")


__all__ = ["CaptureConfig", "CaptureSession", "CaptureStatus", "PoseAdvice", "candidate_poses", "coverage_map",
           "describe_pose", "euler_matrix", "heading_gradients", "pose_scores", "INITIAL_PLAN", "PLAN_FIRST",
           "status_line", "status_screen", *_LIVE_NAMES]
