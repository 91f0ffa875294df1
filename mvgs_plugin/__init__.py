"""MVGS controller: backend-agnostic multi-view regulated training for Gaussian splatting.

    from mvgs_plugin import MVGS, MVGSConfig
    trainer = MVGS(adapter, scene, MVGSConfig.default())
    trainer.fit()

The controller talks to models through the Adapter protocol (mvgs_plugin.protocol) and never
imports a renderer or a model family.
"""

from .camera import Camera, stack_cameras
from .config import CRDConfig, MVADConfig, MVGSConfig, Stage
from .controller import MVGS, EvalResult, StepInfo
from .distributed import Collective, DistributedError
from .protocol import Adapter, DensifyContext, DensifyReport, DistributedAdapter, RenderResult
from .sampler import ViewSampler
from .schedule import StagePlan, StepPlan, ViewSchedule

__all__ = [
    "MVGS", "MVGSConfig", "MVADConfig", "CRDConfig", "Stage", "StepInfo", "EvalResult", "Adapter", "RenderResult", "DensifyContext",
    "DensifyReport", "Camera", "stack_cameras", "ViewSampler", "StagePlan", "StepPlan", "ViewSchedule",
    "DistributedAdapter", "Collective", "DistributedError",
]
