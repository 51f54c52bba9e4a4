"""nn.Modules and their functional twins: losses and denoisers. Pure torch.

``LOSSES`` and ``DENOISERS`` map the names a YAML config uses (``loss: {type: l2}``,
``denoiser: {type: target_aware, radius: 7}``) to the module classes.
"""
from .losses import PIXEL_LOSSES, L1Loss, L2Loss, RelativeL2Loss, l1_loss, l2_loss, relative_l2_loss
from .loi import LOILoss, loi_loss
from .pyramid import GaussianPyramidLoss, MultiScaleL1Loss, MultiScaleL2Loss, gaussian_pyramid_loss, multiscale_l1_loss, multiscale_l2_loss
from .cross_bilateral import CrossBilateralDenoiser, GBufferRegressionDenoiser, cross_bilateral_denoise, gbuffer_regression_denoise
from .target_aware import TargetAwareDenoiser, target_aware_denoise

LOSSES: dict[str, type] = dict(PIXEL_LOSSES)  # name -> loss nn.Module class
DENOISERS: dict[str, type] = {}  # name -> denoiser nn.Module class
LOSSES.update(loi=LOILoss, gp=GaussianPyramidLoss, multiscale_l1=MultiScaleL1Loss, multiscale_l2=MultiScaleL2Loss)

__all__ = ["L1Loss", "L2Loss", "RelativeL2Loss", "l1_loss", "l2_loss", "relative_l2_loss", "LOSSES", "DENOISERS"]
__all__ += ["LOILoss", "loi_loss", "GaussianPyramidLoss", "MultiScaleL1Loss", "MultiScaleL2Loss", "gaussian_pyramid_loss", "multiscale_l1_loss", "multiscale_l2_loss"]
DENOISERS.update(target_aware=TargetAwareDenoiser, cross_bilateral=CrossBilateralDenoiser, gbuffer_regression=GBufferRegressionDenoiser)
__all__ += ["TargetAwareDenoiser", "target_aware_denoise", "CrossBilateralDenoiser", "GBufferRegressionDenoiser", "cross_bilateral_denoise", "gbuffer_regression_denoise"]
