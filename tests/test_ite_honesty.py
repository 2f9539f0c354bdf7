"""ite against the time really left (issue 28): every 13th process of the batch, noise-free and at 1 % noise.

The true time left at each status is the run's end time (the trace's last sample) minus the status's time,
known once the run has ended; ite is judged from half a period after the relay's start to half a period
before the end (autotuner/benchmarks/ite_bench.py says why). Measured on this sample (2026-12-05): within
±30 % on 53 % of the statuses noise-free and 60 % at 1 % noise (main's engine: 19 % and 31 %), ite/true
p10 0.38 and 0.49 (main: 0.14 and 0.28: the 5–10 times short period guess of lag-dominant processes).
Since branch noisy-short the 1 % noise runs are quiet ones (their estimates scatter by a seventh of gain_tol:
docs/experiment.md, "Quiet rules under low noise"), two periods shorter, and ite counts them as it counts
the noise-free runs: within ±30 % on 54 % of the statuses (noise-free 53 %), p10 0.42, median 0.91; ite never
rose (judged) in 2 of the 11 noise-free runs and 6 of the 1 % ones. Since branch ite-three a quiet run's periods
left are the batch's median at the same phase error and change of the period (progress.SETTLED_PERIODS): within
±30 % on 59 % of the statuses noise-free and 59 % at 1 % noise, p10 0.50 and 0.45, never rising in 5 and 6 of 11.
Since branch ite-loads a rise of at most half the shown value stops the clock instead (progress.PAUSE): within
±30 % on 63 % and 57 %, p10 0.50 and 0.45, never rising in 9 and 7 of 11. After the model aim (shorter noise-free
runs) 42 % and 59 %; since branch ite-refit a quiet run whose settled point is one estimate has its own count
(progress.CLEAN_FIT, CLEAN_TYPICAL_PERIODS): 66 % and 59 %, p10 0.65 and 0.46, never rising in 9 and 7 of 11.
Since the model rule (model_rule.py: the quiet runs the model explains end at 1.4–2.9 periods) the quiet runs are
judged on every fourth process (QUIET_SAMPLE, below), where ite counts by what the model's first look says
(progress.CLEAN_TYPICAL_PERIODS): within ±30 % on 70 % and 66 % of the statuses, p10 0.83 and 0.53, median 1.09 and
0.90, p90 1.66 and 1.31, never rising (judged) in 82 % and 85 % of the 34 runs.
"""

from __future__ import annotations

import numpy as np
import pytest

from autotuner.benchmarks.design_bench import default_batch, load_batch
from autotuner.benchmarks.field_bench import SCENARIOS
from dataclasses import replace

from autotuner.benchmarks.ite_bench import HONEST, RISE_TOL, IteRun, field_one, judge, run_one, summarise
from autotuner.engine.experiment.convergence import tolerances
from autotuner.engine.experiment.model_rule import EARLY_SHARE, Fit, bound, first_look, hint
from autotuner.engine.experiment.process_fit import ProcessModel
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import default_sample_time, phase_frequency

SAMPLE = load_batch(default_batch())[::13]
# The quiet runs' sample: every fourth process (34). Since the model rule (model_rule.py) a quiet run's length
# depends on whether the model explains the record, and ite's count on what its first look says: eleven processes
# are too few to judge that by (on the eleven, 2026-12-05: within ±30 % on 71 % of the statuses, p90 1.87 — the
# dead-time-dominant P1-014 and P7-092 before their first rising switch, 0.8 periods in — and ite never rising in 8
# of 11; on every fourth: 70 %, p90 1.54, never rising in 29 of 34).
QUIET_SAMPLE = load_batch(default_batch())[::4]


@pytest.mark.parametrize("noise, within, never_rising", [(0.0, 0.6, 0.8), (0.01, 0.57, 0.6)])
def test_ite_is_within_30_percent_of_the_time_really_left_on_most_statuses(noise: float, within: float,
                                                                           never_rising: float) -> None:
    runs = [run_one(row["expr"], row["id"], noise, every=7) for row in QUIET_SAMPLE]
    judged = [judge(run) for run in runs]
    # Independent of the engine's estimate: the true time left is the trace's end minus the status's time.
    for run, honesty in zip(runs, judged):
        # (A status every 7 samples: the shortest runs, 1.5 periods, have 4 judged.)
        assert run.ok and len(honesty.ratios) > 3, run.id
        assert np.all(run.end - run.t > 0.0) and np.all(run.ite > 0.0), run.id
    summary = summarise(judged)
    assert summary.within >= within, summary
    # Neither 5–10 times low (a first half period taken for the period) nor as high the other way.
    assert summary.p10 >= 0.44 and 0.75 <= summary.median <= 1.3 and summary.p90 <= 1.7, summary
    # ite rises past 2 % between judged statuses only in the runs where a period brought news.
    assert summary.never_rising_judged >= never_rising, summary
    # The statuses within ±30 % are the ones the summary counts.
    ratios = np.concatenate([h.ratios for h in judged])
    assert summary.within == pytest.approx(float(np.mean(np.abs(ratios - 1.0) <= HONEST)))


def test_a_noisy_runs_ite_counts_the_periods_its_averages_take() -> None:
    """At 5 % noise the runs are noisy (the averaged rule) and last 5–20 periods; ite counts the periods the
    average of scattered estimates takes (progress.NOISY_PERIODS). Measured on this sample (2026-12-05): within
    ±30 % on 43 % of the statuses, ite/true p10 0.33, median 0.88, p90 2.78 (before: 17 %, 0.14, 0.34, 1.19)."""
    runs = [run_one(row["expr"], row["id"], 0.05, every=7) for row in SAMPLE]
    summary = summarise([judge(run) for run in runs])
    assert all(run.ok for run in runs)
    assert summary.within >= 0.4, summary
    # No longer a third of the time left at the median; the high tail is what a scatter-driven stop costs.
    assert summary.p10 >= 0.25 and 0.6 <= summary.median <= 1.3 and summary.p90 <= 3.0, summary


def test_a_followed_loads_ite_counts_the_periods_its_stages_take() -> None:
    """Once a load is followed (or a fit of one awaits its confirmation) ite counts what its stage still needs:
    the confirming fit, the estimates since the step, K0 after the bias's flip (progress.load_periods_left).
    Measured on this sample (2026-12-05), a load step early, a small one mid-run and a drift pooled: within ±30 %
    on 34 % of the statuses, ite/true p10 0.19, median 0.70, p90 1.98 (before: 13 %, 0.12, 0.29, 1.29: every
    followed period counted as the last). The statuses before the load is found cannot know of it and stay low."""
    chosen = tuple(s for s in SCENARIOS if s.name in ("load +0.2 early", "load −0.1 mid", "drift +0.3 per 10 periods"))
    runs = [run for row in SAMPLE for run in field_one(row["expr"], row["id"], every=7, scenarios=chosen)]
    assert len(chosen) == 3 and all(run is not None for run in runs)
    judged = [judge(run) for run in runs if run is not None]
    summary = summarise([h for h in judged if len(h.ratios)])
    assert summary.runs >= 30, summary
    assert summary.within >= 0.3 and summary.p10 >= 0.15, summary
    # No longer a third of the time left at the median, and not as high the other way.
    assert 0.6 <= summary.median <= 1.3 and summary.p90 <= 2.2, summary


def test_ite_never_rises_between_statuses_without_news() -> None:
    """Between two statuses with no new sample the estimate stays put; while samples arrive between switches it
    counts down (the hold: a clock's countdown while the estimate agrees with it)."""
    experiment = RelayExperiment(RelayConfig(amp=1.0, expected_period=10.0), mv0=0.0)
    for k in range(30):
        experiment.step(0.1 * k, 0.0)
    first = experiment.status().ite
    assert experiment.status().ite == first
    experiment.step(3.0, 0.0)
    assert experiment.status().ite < first


def stamped_run(share: float, seed: int) -> IteRun:
    """tests/test_handshake.py's loop (exp(−s)/(2s+1), 40 samples per period, amp 5, a time limit of 500 s: the
    period it implies, 2.5 s, is half the plant's) as a daemon samples a simulated PLC, each PV stamped up to
    ``share`` of the sample time off the instant it was taken (uniform, ``seed``); the status after every sample."""
    process = parse_process("exp(-s)/(2*s+1)")
    ts = default_sample_time(process) * 100 / 40
    rng = np.random.default_rng(seed)
    sim = PlantSim(process, ts, pv0=50.0, mv0=50.0)
    experiment = RelayExperiment(RelayConfig(amp=5.0, time_limit=500.0), mv0=50.0)
    t, ite, relay = [], [], []
    while not experiment.done:
        stamp = sim.t + share * ts * rng.uniform(-1.0, 1.0)
        sim.advance(experiment.step(stamp, sim.measure()))
        status = experiment.status()
        if status.code is None:
            t.append(stamp), ite.append(status.ite), relay.append(status.relay)
    relays = np.array(relay)
    # (Judged from the first rising switch on: before it the period implied by the time limit, half the plant's,
    # is all ite knows, and the time the relay has run pushes its guess up.)
    rising = int(np.flatnonzero((relays[:-1] < 0) & (relays[1:] > 0))[0]) + 1
    period = 2.0 * np.pi / phase_frequency(process, 135.0)
    return IteRun(f"{share}/{seed}", np.array(t), np.array(ite), t[-1] + ts, t[rising] - 0.5 * period, period,
                  0.0, experiment.code == 0)


@pytest.mark.parametrize("share", [0.015, 0.03, 0.06])
def test_ite_of_a_daemon_sampled_plc_falls_from_the_first_rising_switch_on(share: float) -> None:
    """A daemon's samples of a simulated PLC are stamped off the PV's instants, which the model's fits read as noise
    of 1–6e-3 of the swing: ite's hint said the model explained the record from a fit to the first half period,
    then did not, and the period measured at the second rising switch replaced the one the time limit implies.
    Measured (2026-12-05, six seeds per share 0.015, 0.03, 0.06, judged from the first rising switch to half a
    period before the end): main's ite rose by 1.0–2.2 times in every run, ite/true p10 0.11, 0.29, 0.30, median
    0.27, 0.81, 0.80, within ±30 % on 10, 60, 56 % of the statuses; now it rises in none, p10 0.57, median 0.71,
    0.64, 0.71, within ±30 % on 47, 41, 46 % (the countdown held where the half period measured at the first
    rising switch raised the estimate: progress.PAUSE)."""
    runs = [stamped_run(share, seed) for seed in range(3)]
    judged = [judge(run) for run in runs]
    assert all(run.ok for run in runs) and all(len(h.ratios) > 50 for h in judged)
    assert all(h.judged_rise <= RISE_TOL for h in judged), [h.judged_rise for h in judged]
    summary = summarise(judged)
    # Not a countdown frozen low: within a factor of two of the time left, and near it at the median.
    assert summary.p10 >= 0.5 and summary.median >= 0.55 and summary.p90 <= 1.3, summary


def test_a_rough_fit_says_the_model_explains_the_record_only_where_its_noise_leaves_the_rule_room() -> None:
    """ite's hint (model_rule.first_look, hint): a fit within the rule's bound explains the record whatever the
    noise (the first half period's third difference reads the cycle's curvature, up to 3.4e-4 of the swing on the
    noise-free batch); a rough one only on a record whose noise is within the bound, and not after a NO."""
    tol = tolerances(RelayConfig(amp=1.0))
    early = EARLY_SHARE * tol.gain_tol
    exact = ProcessModel(k0=1.0, t1=2.0, t2=0.0, delay=1.0, misfit=0.5 * bound(tol))
    rough = replace(exact, misfit=0.5 * (bound(tol) + early))
    quiet, noisy = 0.5 * bound(tol), 0.5 * (bound(tol) + early)
    assert first_look(exact, tol, noisy) is Fit.EXPLAINS
    assert first_look(rough, tol, quiet) is Fit.EXPLAINS
    assert first_look(rough, tol, noisy) is Fit.NO
    assert first_look(replace(rough, misfit=2.0 * early), tol, quiet) is Fit.NO
    assert first_look(None, tol, quiet) is Fit.NO
    assert hint(rough, None, 5.0, tol, quiet, Fit.EXPLAINS) is Fit.EXPLAINS
    assert hint(rough, None, 5.0, tol, quiet, Fit.NO) is Fit.NO
