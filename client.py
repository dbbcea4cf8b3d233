"""The mapper's public API: poses from a running vtolpose over Zenoh, without OpenCV.

    from vtolpose.client import PoseClient, PoseUnavailable

See :mod:`vtolpose.service.outputs.pose_client` for the details; this path stays stable when
the service's modules move.
"""

from vtolpose.estimator import OutsideHistory, PoseWindow
from vtolpose.service.outputs.pose_client import Pose, PoseClient, PoseUnavailable, ServiceUnreachable
from vtolpose.service.outputs.zenoh_session import ZenohSettings

__all__ = ["OutsideHistory", "Pose", "PoseClient", "PoseUnavailable", "PoseWindow", "ServiceUnreachable", "ZenohSettings"]
