"""experiments/bench_allocator.py's summary of child runs (constructed runs, no children)."""

from __future__ import annotations

import sys

import pytest


def runs(seconds_default, seconds_kept, results=(1.0, 1.0), steps=(None, None),
         seconds_huge_pages=None):
  def run(seconds, result, step):
    return {"seconds": seconds, "result": result, "steps": step, "process_system_seconds": 0.0,
            "minor_page_faults": 0, "peak_rss_bytes": 0}
  measured = {"glibc_default": [run(s, results[0], steps[0]) for s in seconds_default],
              "keep_freed_memory": [run(s, results[1], steps[1]) for s in seconds_kept]}
  if seconds_huge_pages is not None:
    measured["huge_pages"] = [run(s, results[0], steps[0]) for s in seconds_huge_pages]
  return measured


def test_fixed_work_reports_the_speed_up_and_whether_results_agree(experiment_script):
  bench = experiment_script("bench_allocator")
  summary = bench.summarise("nerf_train", runs([50.0, 54.0], [34.0, 36.0]))
  # The median of the rounds' ratios (50 / 34 and 54 / 36).
  assert summary["speedup_over_glibc_default"] == {
      "keep_freed_memory": pytest.approx((50.0 / 34.0 + 1.5) / 2, abs=1e-3)}
  assert summary["same_results"]
  assert bench.speedups("nerf_train", runs([50.0, 54.0], [25.0, 36.0]),
                        "keep_freed_memory") == pytest.approx([2.0, 1.5])
  assert not bench.summarise("nerf_train", runs([50.0], [34.0], results=(26.7, 26.8)))[
      "same_results"]


def test_a_time_budget_reports_the_steps_reached(experiment_script):
  bench = experiment_script("bench_allocator")
  budget = runs([300.0], [300.0], results=(31.7, 32.2), steps=(1700, 2550))
  summary = bench.summarise("nerf_budget", budget)
  assert summary["speedup_over_glibc_default"]["keep_freed_memory"] == pytest.approx(1.5)
  assert summary["keep_freed_memory"]["result"] == pytest.approx(32.2)
  assert "same_results" not in summary  # A budget gives each mode its own result.
  assert bench.speedups("nerf_budget", budget, "keep_freed_memory") == pytest.approx([1.5])


def test_every_mode_is_compared_with_glibc_default(experiment_script):
  bench = experiment_script("bench_allocator")
  summary = bench.summarise("unet_forward", runs([12.0], [12.0], seconds_huge_pages=[10.0]))
  assert summary["speedup_over_glibc_default"] == {
      "keep_freed_memory": pytest.approx(1.0), "huge_pages": pytest.approx(1.2)}
  assert summary["huge_pages"]["seconds"] == pytest.approx(10.0)


def test_the_figure_has_a_row_per_workload_and_mode(experiment_script, tmp_path):
  bench = experiment_script("bench_allocator")
  result = {"workloads": {"nerf_train": {"runs": runs([50.0], [25.0])},
                          "update": {"runs": runs([0.75], [0.9], seconds_huge_pages=[0.7])}}}
  bench.write_figure(tmp_path / "figure.png", result)
  assert (tmp_path / "figure.png").stat().st_size > 0


@pytest.mark.parametrize("workloads", [["viewer_frames"], ["nerf_train", "nerf_eval"]])
def test_workloads_on_a_trained_run_need_one(experiment_script, monkeypatch, capsys, workloads):
  bench = experiment_script("bench_allocator")
  monkeypatch.setattr(sys, "argv", ["bench_allocator.py", "--workloads", *workloads])
  with pytest.raises(SystemExit):
    bench.main()
  assert "need --run RUN" in capsys.readouterr().err
