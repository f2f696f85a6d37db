"""Verification layer: distinct hypotheses from one consistency graph, their registration,
point-level evidence and the decision (``valid``, ``confidence``, margin, runner-up).

A loop closure accepted by a SLAM back end is trusted blindly, so the matcher keeps a result
only when the evidence says it is right and no distinct rival explains the data about as well.
"""

from graffmatch.verification.config import VerificationConfig
from graffmatch.verification.decision import Hypothesis, decide
from graffmatch.verification.evidence import SupportCloud, landmark_overlap, support_cloud
from graffmatch.verification.verify import Evidence, verify_graph

__all__ = [
    "Evidence",
    "Hypothesis",
    "SupportCloud",
    "VerificationConfig",
    "decide",
    "landmark_overlap",
    "support_cloud",
    "verify_graph",
]
