"""Lightning-side training: the module, the views' data module, callbacks and the CLI."""
from .callbacks import CurvePlotter, ImageWriter, NonFiniteLossGuard, ParameterProjection, StepTimer
from .data import ViewDataModule, load_image
from .module import InverseRenderingModule, NonFiniteLossError
from .parameters import ParameterConfig, SceneParameter

__all__ = [
    "InverseRenderingModule", "ViewDataModule", "ParameterConfig", "SceneParameter", "NonFiniteLossError",
    "ParameterProjection", "StepTimer", "NonFiniteLossGuard", "ImageWriter", "CurvePlotter", "load_image",
]
