"""Every figure of resloc, in one place (matplotlib is imported lazily, inside each function,
with the Agg backend; importing this package needs numpy only).

* :mod:`~resloc.experiments.plots.core`: ``pyplot``, one style per estimator, saving;
* :mod:`~resloc.experiments.plots.run`: a run's trajectories, MSLE, transmissions;
* :mod:`~resloc.experiments.plots.bands`: studies over seeds (report, sweeps);
* :mod:`~resloc.experiments.plots.mrclam`: an MRCLAM replay.
"""

from resloc.experiments.plots.bands import (
    Curve,
    band_figure,
    errorbar_figure,
    raster_figure,
    xy_errorbar_figure,
)
from resloc.experiments.plots.core import (
    COLORS,
    ESTIMATOR_STYLES,
    estimator_label,
    estimator_style,
    pyplot,
)
from resloc.experiments.plots.mrclam import plot_mrclam_errors, plot_mrclam_trajectories
from resloc.experiments.plots.run import (
    draw_zones,
    link_rates,
    plot_msle,
    plot_run,
    plot_trajectories,
    plot_transmissions,
)

__all__ = [
    "COLORS",
    "ESTIMATOR_STYLES",
    "Curve",
    "band_figure",
    "draw_zones",
    "errorbar_figure",
    "estimator_label",
    "estimator_style",
    "link_rates",
    "plot_mrclam_errors",
    "plot_mrclam_trajectories",
    "plot_msle",
    "plot_run",
    "plot_trajectories",
    "plot_transmissions",
    "pyplot",
    "raster_figure",
    "xy_errorbar_figure",
]
