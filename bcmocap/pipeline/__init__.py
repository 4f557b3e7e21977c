"""The user's workflow end to end: ``bcmocap run`` (:mod:`.run`), its settings (:mod:`.config`), the metric
world it works in (:mod:`.world`) and the files it leaves (:mod:`.outputs`)."""

from ..lazy_exports import lazy_exports

# Imported on first use (PEP 562): `bcmocap view` starts its server before it imports JAX.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "STAGES": "run", "RunConfig": "config", "Similarity": "world", "load_config": "config", "load_model": "run",
    "load_motion": "run", "run_pipeline": "run", "transform_model": "world"})
