"""nn.Modules and their functional twins (losses, and the denoisers as their issue lands). Pure torch."""
from .losses import L1Loss, L2Loss, RelativeL2Loss, l1_loss, l2_loss, relative_l2_loss

__all__ = ["L1Loss", "L2Loss", "RelativeL2Loss", "l1_loss", "l2_loss", "relative_l2_loss"]
