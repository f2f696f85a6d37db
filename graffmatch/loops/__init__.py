"""Loop closure over whole drives: landmark database, retrieval, verification, pose graph."""

from graffmatch.loops.database import LandmarkDatabase, load_landmarks, save_landmarks
from graffmatch.loops.descriptor import DescriptorConfig, landmark_descriptor
from graffmatch.loops.detector import LoopDetector, LoopDetectorConfig
from graffmatch.loops.plan import verify_query
from graffmatch.loops.quickcheck import QuickCheckConfig, QuickIndex, quick_check, quick_index
from graffmatch.loops.retrieval import RetrievalConfig, eligible_count, make_retriever
from graffmatch.loops.verify import LoopClosure, VerificationConfig, landmark_agreement

__all__ = [
    "DescriptorConfig",
    "LandmarkDatabase",
    "LoopClosure",
    "LoopDetector",
    "LoopDetectorConfig",
    "QuickCheckConfig",
    "QuickIndex",
    "RetrievalConfig",
    "VerificationConfig",
    "eligible_count",
    "landmark_agreement",
    "landmark_descriptor",
    "load_landmarks",
    "make_retriever",
    "quick_check",
    "quick_index",
    "save_landmarks",
    "verify_query",
]
