"""Monte Carlo and adaptive Multilevel Monte Carlo drivers (SPEC section 5).

Symbols follow SPEC section 5 and :mod:`rough_uq.multilevel.statistics`,
:mod:`~rough_uq.multilevel.rates` and :mod:`~rough_uq.multilevel.allocation`: ``Q_l`` the
quantity of interest on level ``l`` (mesh ``h_l = h_0 2^-l``),
``Y_l = Q_l - Q_{l-1}`` (``Y_0 = Q_0``), ``V_l = Var(Y_l)``, ``C_l`` the mean
cost of a level-``l`` sample, ``|E[Y_l]| ~ 2^(-alpha l)``,
``V_l ~ 2^(-beta l)``, ``C_l ~ 2^(gamma l)``; ``eps`` (``tol``) bounds the
root-mean-square error, ``MSE = sum_l V_l / N_l + bias^2 <= eps^2``, and
``theta`` is the share of ``eps^2`` given to the squared bias.

The sampler contract
--------------------
A level sampler is any callable ``sampler(level, sample_indices) ->
(fine, coarse, cost)``:

* ``sample_indices``: int64 array of shape ``(n,)``;
* ``fine``, ``coarse``: shape ``(n,)`` (one QoI) or ``(n, n_qoi)``, the
  QoIs ``Q_l`` and ``Q_{l-1}`` of the *same* random input (``coarse`` is 0
  on level 0);
* ``cost``: shape ``(n,)`` (a scalar is broadcast), the cost of each sample,
  seconds or model units, ``>= 0``.

The sampler derives all randomness from ``(level, index)`` (the pipeline uses
``SeedSequence(seed, spawn_key=(stage, level, index))``), so the engine never
touches a random generator and every sample can be recomputed. **The engine
asks for contiguous new indices per level**: the samples of level ``l`` are
indices ``0, 1, 2, ...`` in that order, each requested exactly once, batch
after batch. A sampler backed by a cache (the pipeline's study file) can
therefore serve the indices it already holds and compute only the rest; a
resumed run that gets the stored values and costs back makes the same
decisions and so replays the same sequence of requests.

Drivers are generators
----------------------
:func:`iter_mlmc` and :func:`iter_mc` yield small frozen events:
:class:`PlanUpdated` (levels and samples planned/done per level),
:class:`BatchDone` (one batch: its indices, values and costs, plus progress)
and finally :class:`Finished` (the :class:`EstimationResult`). The CLI
consumes them for progress bars and store writes; :func:`mlmc` and
:func:`mc` simply run them to the end.

One loop serves both (:mod:`~rough_uq.multilevel.drivers.loop`): a run holds a
hierarchy of levels (its samples, planned ``N_l`` and spent cost) and, round
after round, draws the missing samples of every level in batches, re-plans
``N_l`` and, once the samples are (nearly) complete, decides whether to stop.
What differs is the run's state object: the MLMC run refits the rates,
allocates over the levels, checks the Richardson ratios and the bias and may
add a level; plain MC is the one-level hierarchy at its level, sampled as
``Q_level`` alone, whose ``N`` follows ``Var(Q_level)`` and which stops once
its samples are drawn.

Submodules
----------
* :mod:`~rough_uq.multilevel.drivers.events`: the events and the result of a run (:class:`EstimationResult`).
* :mod:`~rough_uq.multilevel.drivers.samples`: the samples of a level; the sampler calls, checked against
  the contract above.
* :mod:`~rough_uq.multilevel.drivers.planning`: the rates a run plans with; the costs and variances it
  allocates with.
* :mod:`~rough_uq.multilevel.drivers.hierarchy`: a run's hierarchy (samples, plan, spent cost); what a
  budget affords.
* :mod:`~rough_uq.multilevel.drivers.loop`: the driver loop shared by MC and MLMC; the sizes of its rounds.
* :mod:`~rough_uq.multilevel.drivers.adaptive`: adaptive MLMC (the algorithm below), its start from a
  screening, the refusal of plans too large.
* :mod:`~rough_uq.multilevel.drivers.plain_mc`: plain Monte Carlo on one level.

Their docstrings call this one "the module docstring". The package re-exports
the names of ``__all__`` and the few others that the rest of roughuq imports
from it; names with a leading underscore are private to the package (its
modules share them). A name is looked up in the submodule that defines it:
a test that replaces one (``monkeypatch.setattr``) patches that submodule,
since setting it on the package changes no caller inside.

Adaptive MLMC
-------------
Giles (2015), algorithm 1, with the refinements of his ``mlmc`` code:

1. Start on levels ``0..min_finest_level`` with ``n_initial`` samples each
   (Giles' ``N0``: nothing is known about the levels yet), or from a
   screening table: the finest level and ``N_l`` of
   :func:`~rough_uq.multilevel.allocation.plan`, at least 2 per level (so that every level
   has a sample variance). With a screening, the screening's and the run's
   ``Y_l`` of a level both sampled are independent samples of the same
   level: ``V_l`` is their pooled variance, for the allocation and for the
   statistical error, and ``E[Y_l]`` their count-weighted mean, for the bias
   estimate and the fit of ``alpha`` (step 3; its standard error
   ``sqrt(V_l / (N_run + N_screening))`` for the Richardson ratio check). The
   estimate itself uses the run's samples only. Without a screening, every
   level keeps at least ``n_initial`` samples.
2. Draw the missing samples level by level, each level all it misses, in
   batches of at most ``batch_size``, so that the plans and the result do not
   depend on the batch size (where ``max_cost`` cannot pay what the current plan
   still misses, at the costs per sample measured so far, a round draws on
   each level the share of its missing samples that the budget left pays,
   so that a run the budget stops has its samples in about the planned
   ratio: with equal batches, one stopped by ``max_cost = 2`` had 351 / 350
   / 342 samples where its plan asked for 15008 / 2237 / 616, and a
   statistical error of 0.19 where the same cost in the plan's ratio gives
   about 0.11. A budget that pays every plan of the run changes nothing; one
   that an early plan overshoots draws that round differently, and so may
   end with other counts than the run without a budget); after each round
   re-estimate ``V_l``, ``C_l`` and refit the
   rates (unless given), and update ``N_l = ceil((1-theta)^-1 eps^-2
   sqrt(V_l/C_l) sum_k sqrt(V_k C_k))`` (maximum over QoIs; never below the
   samples already drawn). For ``l >= 2``, ``V_l`` is floored at
   ``V_{l-1} 2^-beta / 2`` so that a few lucky samples cannot starve a level,
   and a sampled ``V_l`` (``l >= 1``) at half the sampled ``V_{l+1}``, so
   that a level whose samples all missed a rare difference is not starved
   either (:data:`~rough_uq.multilevel.drivers.planning._FLOOR_FROM_ABOVE`).
3. Once every level has (nearly, within 1%) its planned samples, estimate
   the remaining bias ``max(c_alpha 2^(-alpha L), |E[Y_L]|, |E[Y_{L-1}]|
   2^-alpha, |E[Y_{L-2}]| 2^(-2 alpha)) / (2^alpha - 1)``
   (:func:`~rough_uq.multilevel.rates.estimated_bias`: the tail sum of
   the ``alpha`` model, whose least-squares line through all levels above the
   base is robust against a finest mean that happens to be near 0, and never
   below what the three finest difference levels predict; the tail is summed
   at ``alpha`` at most 2, and where ``alpha`` is a line through two means or
   the two finest means differ in sign, at most at the decay they confirm,
   from those two means only: module docstring of
   :mod:`~rough_uq.multilevel.rates`; the rule :func:`plan` uses too, beyond
   the screened levels at the rate of the finest screened pair, so a run and
   the screening's prediction agree). If it exceeds ``sqrt(theta) eps`` for
   some QoI, add level ``L+1`` with ``V_{L+1} = V_L 2^-beta``, ``C_{L+1} =
   C_L 2^gamma`` (``gamma`` the larger of the fitted one and the problem's
   ``gamma_beyond``: :attr:`~rough_uq.multilevel.rates.Rates.gamma_extrapolated`)
   and go to 2. Each time the plan changes, a run whose bias so
   far, carried to ``max_level`` at that rate, is above twice its share warns
   before drawing the plan's samples (:meth:`~rough_uq.multilevel.drivers.adaptive._MlmcRun.check_reach`).
4. Stop when all planned samples are drawn and the bias test passes
   (``stop_reason = "tol_met"``), when the bias test fails on ``max_level``
   (``"max_level"``), or before a batch would exceed ``max_cost``
   (``"max_cost"``). ``tol_met`` is then ``sum_l V_l/N_l + bias^2 <= eps^2``
   for every QoI, with the sample variances and the remaining bias of the
   estimate, whose finest level is the finest one sampled (``max_cost`` may
   stop a run before it samples a level it added). The bias is estimated
   only once the run has sampled its levels ``base..max(min_finest_level,
   base + 2)``, the fewest its bias test ever uses (``is_bias_estimated``);
   a run that ``max_cost`` stops earlier reports the bias as 0, not
   estimated, and does not meet its tolerance, however small its
   statistical error (it plainly telescopes its sampled levels, without
   Richardson extrapolation).

Richardson extrapolation (``richardson=True``)
-----------------------------------------------
The estimate becomes ``sum_{l<L} mean(Y_l) + w mean(Y_L)``,
``w = 2^alpha / (2^alpha - 1)`` with the driver's ``alpha`` (see
:mod:`rough_uq.multilevel.richardson` for the formulas and the remaining-bias estimate).
While it is *active*, the allocation gives the finest level the variance
``w^2 V_L`` and step 3 tests the extrapolated estimate's remaining bias
(:func:`~rough_uq.multilevel.richardson.richardson_bias`) instead of the plain one. It is
active from the start if the screening's plan is extrapolated
(:func:`~rough_uq.multilevel.allocation.plan` with ``richardson``), else *pending* (plain
MLMC) until the run has ``RICHARDSON_MIN_LEVELS`` levels above its base
level. Each time the samples
are complete the run's own level means (standard errors from the pooled
``V_l``) are checked with :func:`~rough_uq.multilevel.richardson.ratio_instability`; a
failed check *refuses* the extrapolation for the rest of the run (a
:class:`RichardsonRefused` event, ``EstimationResult.richardson =
"refused"`` with the reason, an :class:`EstimationWarning`) and the run goes
on as plain MLMC, adding levels if the plain bias test asks for them. So
does a screening whose means fail the check (two levels ``>= 1`` suffice
there), and a run that ends while still pending.

Fitted rates are floored at 0.5 (as in Giles' code) so that extrapolation
stays sane, and when a rate cannot be fitted (fewer than two usable levels,
e.g. all ``E[Y_l] = 0``) the screening rates or 0.5 are used instead.

Beyond the mean
---------------
The same samples give the MLMC estimate of ``Var(Q)``:
``sum_l [s^2(Q_l) - s^2(Q_{l-1})]`` over the level-``l`` samples (both with
the ``n - 1`` normalisation, so each term is unbiased for
``Var(Q_l) - Var(Q_{l-1})``), with standard error
``sqrt(sum_l se_l^2)``, ``se_l`` the plug-in fourth-moment standard error of
:func:`~rough_uq.multilevel.statistics.level_statistics`. Its bias
``Var(Q) - Var(Q_L)`` is not controlled.
"""

from __future__ import annotations

from rough_uq.multilevel.allocation import Plan, plan
from rough_uq.multilevel.drivers.adaptive import (
    check_finest_levels,
    iter_mlmc,
    mlmc,
    refuse_large_plan,
    refuse_large_start,
    starting_forecast,
    starting_plan,
    starting_samples,
)
from rough_uq.multilevel.drivers.events import (
    BatchDone,
    EstimationResult,
    Event,
    Finished,
    PlanUpdated,
    RichardsonRefused,
)
from rough_uq.multilevel.drivers.hierarchy import affordable_count
from rough_uq.multilevel.drivers.plain_mc import iter_mc, mc
from rough_uq.multilevel.drivers.planning import planning_rates
from rough_uq.multilevel.drivers.samples import Sampler
from rough_uq.multilevel.rates import Rates, fit_rates
from rough_uq.multilevel.statistics import EstimationWarning, LevelStatistics, diagnose, level_statistics

# Not in __all__, but imported from here: the limit of a plan's samples (by the runs, the pipeline and the CLI),
# the rate floor (by the records and the targets), and the helpers the variance and CDF driver
# (rough_uq.multilevel.targets) shares.
from rough_uq.multilevel.drivers.adaptive import MAX_PLANNED_SAMPLES as MAX_PLANNED_SAMPLES
from rough_uq.multilevel.drivers.loop import budget_share as budget_share
from rough_uq.multilevel.drivers.loop import checked_batch_cap as checked_batch_cap
from rough_uq.multilevel.drivers.loop import round_counts as round_counts
from rough_uq.multilevel.drivers.planning import fill_costs as fill_costs
from rough_uq.multilevel.drivers.planning import planning_variances as planning_variances
from rough_uq.multilevel.drivers.samples import call_sampler as call_sampler
from rough_uq.multilevel.drivers.samples import check_optional_positive as check_optional_positive
from rough_uq.multilevel.rates import RATE_FLOOR as RATE_FLOOR

__all__ = [
    "BatchDone",
    "EstimationResult",
    "EstimationWarning",
    "Event",
    "Finished",
    "LevelStatistics",
    "Plan",
    "PlanUpdated",
    "Rates",
    "RichardsonRefused",
    "Sampler",
    "affordable_count",
    "check_finest_levels",
    "diagnose",
    "fit_rates",
    "iter_mc",
    "iter_mlmc",
    "level_statistics",
    "mc",
    "mlmc",
    "plan",
    "planning_rates",
    "refuse_large_plan",
    "refuse_large_start",
    "starting_forecast",
    "starting_plan",
    "starting_samples",
]
