"""The user's workflow end to end: ``bcmocap run`` (:mod:`.run`), its settings (:mod:`.config`), the metric
world it works in (:mod:`.world`) and the files it leaves (:mod:`.outputs`)."""

from .config import RunConfig, load_config
from .run import STAGES, load_model, load_motion, run_pipeline
from .world import Similarity, transform_model

__all__ = ["STAGES", "RunConfig", "Similarity", "load_config", "load_model", "load_motion", "run_pipeline", "transform_model"]
