"""``torchir tune CONFIG``: measure the speed/accuracy trade of the techniques that apply to a
run's config, and write the config with the best of them filled in.

For each setting (samples per pixel, pixel sampling, ReSTIR, a denoiser; the LOI loss in place
of an image loss) it measures, through the real trainer, the error of the parameters' gradient
at the starting point against a high-spp reference and the seconds per step, and ranks the
settings by their *window error*: the error of the gradient an optimiser averages over its window
of ``T`` seconds, ``sqrt(persistent² + spread² * seconds_per_step / T)``, where the persistent part
(bias, or error kept from step to step) does not average out (:func:`window_error`); a short
training run of the best few gives how fast each lowers the error per second. The default search
is a coordinate search with short trials and a longer look at the best few; ``full=True`` measures
the whole grid.

Modules: :mod:`.config` (reading the YAML, writing the tuned copy), :mod:`.space` (which
settings apply), :mod:`.measure` (the trials), :mod:`.search` (scores, the Pareto front, the
search orders), :mod:`.report` (table and plot), :mod:`.run` (:func:`tune`).
"""
from .run import EFFORTS, default_out, tune
from .search import OPTIMISER_WINDOW, equal_time_error, pareto_front, window_error
from .space import Setting, Space, enumerate_space

__all__ = ["tune", "default_out", "EFFORTS", "OPTIMISER_WINDOW", "equal_time_error", "window_error", "pareto_front", "Setting",
           "Space", "enumerate_space"]
