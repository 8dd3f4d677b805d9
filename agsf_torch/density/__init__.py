"""Exact reference densities and a proper density score for comparing filters.

The **density score** of a filter at time ``t`` is the expected log-density of its
mixture ``p̂`` under the *exact* filtering density ``p`` of the filter's own model
(same prior, same SDE, same inputs, same measurements),
``S(p̂) = E_{x∼p}[log p̂(x)] = −H(p) − KL(p ‖ p̂)``: a proper scoring rule whose
differences between filters are differences of KL divergences from the exact density.
``p`` is represented by weighted samples from :class:`PosteriorReference`, a
sequential Monte Carlo sampler whose particles are whole paths of the model's Itô SDE.

One concept per module:

* :mod:`~agsf_torch.density.charts` — the Euclidean and the folded MRP chart
  (:data:`CHARTS`, :func:`chart_for`, :func:`canonical_points`) and the log-density of
  a Gaussian mixture in a chart (:func:`mixture_log_density`);
* :mod:`~agsf_torch.density.score` — the density score and its lineage-aware standard
  error (:func:`density_score`);
* :mod:`~agsf_torch.density.reference` — the sampler (:class:`PosteriorReference`):
  forecast (:mod:`agsf_torch.sample_paths`), bootstrap update, resampling (:mod:`agsf_torch.weighted_samples`,
  whose :func:`effective_sample_size` is exported here too), per-step diagnostics (:class:`ReferenceStepRecord`);
* :mod:`~agsf_torch.density.redraw` — its path-space redraw where the bootstrap
  collapses: Laplace (Gauss–Newton) fits of the posterior of ``x₀`` along the
  noise-free flow, and importance sampling over all frames;
* :mod:`~agsf_torch.density.proposal` — the redraw's proposal for ``x₀``
  (:class:`InitialStateProposal`);
* :mod:`~agsf_torch.density.frames` — a measurement frame as the sampler records it.
"""

from ..weighted_samples import effective_sample_size
from .charts import CHARTS, canonical_points, chart_for, mixture_log_density
from .frames import ReferenceStepRecord
from .proposal import InitialStateProposal
from .reference import PosteriorReference
from .score import density_score

__all__ = [
    "CHARTS",
    "chart_for",
    "canonical_points",
    "mixture_log_density",
    "effective_sample_size",
    "density_score",
    "ReferenceStepRecord",
    "InitialStateProposal",
    "PosteriorReference",
]
