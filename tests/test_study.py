"""Studies: variants through the cache, metrics from artifacts, report and plots."""
from __future__ import annotations

import csv

import pytest
from click.testing import CliRunner

from pipeline import ConfigError
from pipeline.cli import main
from pipeline.study import run_study

from conftest import REPO, ran

STUDY = """\
study_version: 1
name: toy_study
base: toy.yaml
sweep:
  simulate.steps: [1, 2, 4]
outputs: [particles]
time: simulate
metrics:
  - {name: error, file: particles/stats.json, key: stats.error, label: made-up error}
"""


def test_study_runs_variants_and_reports(toy_config):
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY)
    results, out = run_study(path)
    assert [r.overrides["simulate.steps"] for r in results] == [1, 2, 4]
    assert [r.metrics["error"] for r in results] == [1.0, 0.5, 0.25]
    rows = list(csv.reader(open(out / "study.csv")))
    assert rows[0] == ["simulate.steps", "simulate_seconds", "simulate_cpu_seconds", "error", "variant-error"] and len(rows) == 4
    assert all(row[-1] == "" for row in rows[1:])  # no variant failed
    assert (out / "error_vs_time.png").stat().st_size > 1000
    assert ran(toy_config, "simulate") == 3
    run_study(path)  # cached: nothing recomputed
    assert ran(toy_config, "simulate") == 3 and ran(toy_config, "render") == 0


def test_study_errors(toy_config):
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("mode", "x").replace("sweep:", "sweeps:"))
    # the key the user wrote, its line and the field it was meant to be (it said only "sweep: required field
    # is missing", with no line)
    with pytest.raises(ConfigError, match=r"study\.yaml:\d+: sweeps: unknown key \(did you mean sweep\?\)"):
        run_study(path)
    path.write_text(STUDY.replace("file: particles/stats.json, key: stats.error", "function: toy_stages:nothing"))
    with pytest.raises(ConfigError, match="function 'toy_stages:nothing' not found"):
        run_study(path)
    path.write_text(STUDY.replace("key: stats.error", "function: toy_stages:scaled_error"))
    with pytest.raises(ConfigError, match="either file and key, or function"):
        run_study(path)
    result = CliRunner().invoke(main, ["study", str(toy_config.parent / "missing.yaml")])
    assert result.exit_code == 2 and "study file not found" in result.stderr


def test_study_metric_from_a_function(toy_config):
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("file: particles/stats.json, key: stats.error",
                                  "function: 'toy_stages:scaled_error', args: {factor: 10}"))
    results, _ = run_study(path)
    assert [r.metrics["error"] for r in results] == [10.0, 5.0, 2.5]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_metric_reading_another_variant_sees_this_studys_run_of_it(toy_config, workers):
    """A metric that reads another variant (the distance to the finest run) was computed as each variant
    ended: before the reference had run (listed after it, or beside it with --workers 2), or against the
    reference's run of the study's former config (a user's sweep: wrong distances, exit 0). Metrics are
    measured once every variant has run."""
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("file: particles/stats.json, key: stats.error",
                                  "function: 'toy_stages:minus_reference', args: {reference: {steps: 4}}"))
    results, _ = run_study(path, workers=workers)
    assert [r.metrics["error"] for r in results] == [0.75, 0.25, 0.0] and not any(r.error for r in results)


STUDIES = sorted(p for p in (REPO / "configs").rglob("*.yaml") if "out" not in p.parts and "study_version" in p.read_text())


@pytest.mark.parametrize("path", STUDIES, ids=lambda p: p.stem)
def test_shipped_studies_are_valid(path):
    from pipeline.study import _metric_function, load_study

    study = load_study(path)
    assert (path.parent / study.base).is_file()
    for m in study.metrics:
        if m.function is not None:
            _metric_function(m.function, path)
            ref = m.args.get("reference")
            assert ref is None or (path.parent / ref).is_file()


def test_a_study_never_writes_over_a_users_file(toy_config):
    """The report's files are published as a run's outputs are: a user's own study.csv in the report folder
    stops the study before any variant runs (it was overwritten), and a name that is not a plain folder
    name ('..' wrote the report beside the study file) is refused."""
    from pipeline.publish import OutputRefused

    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY)
    out = toy_config.parent / "mine"
    out.mkdir()
    (out / "study.csv").write_text("my numbers")
    with pytest.raises(OutputRefused, match="study.csv: a file the pipeline did not create"):
        run_study(path, out_dir=out)
    assert (out / "study.csv").read_text() == "my numbers" and ran(toy_config, "simulate") == 0
    _, published = run_study(path)  # its own folder: published, then replaced on the next run
    run_study(path)
    assert sorted(p.name for p in published.iterdir() if p.is_file() and not p.name.startswith(".")) == [
        "error_vs_time.png", "study.csv", "study.json", "study.md"]
    for name in ("..", ".", ".hidden"):
        path.write_text(STUDY.replace("name: toy_study", f"name: '{name}'"))
        with pytest.raises(ConfigError, match="name"):
            run_study(path)


def test_study_mistakes_are_found_before_or_named_after(toy_config):
    """A swept value that no variant can take, a cost stage the outputs do not run, a metric key or file the
    variants do not have: one line naming the study, variant or metric (a bad value was found after the
    variants before it had run; a missing key gave an empty column; time: render with particle outputs read
    0 s)."""
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("[1, 2, 4]", "[1, oops]"))
    with pytest.raises(ConfigError, match=r"study.yaml: variant steps-oops: .*simulate.steps"):
        run_study(path)
    assert ran(toy_config, "simulate") == 0
    path.write_text(STUDY.replace("time: simulate", "time: render"))
    with pytest.raises(ConfigError, match="time: render is not a stage the outputs"):
        run_study(path)
    path.write_text(STUDY.replace("key: stats.error", "key: stats.eror"))
    with pytest.raises(ConfigError, match="metric error: particles/stats.json of variant steps-1 has no key stats.eror; "
                                          "the other variants were not run"):
        run_study(path)
    assert ran(toy_config, "simulate") == 1  # said on the first variant, not after all three
    path.write_text(STUDY.replace("file: particles/stats.json", "file: particles/nothere.json"))
    with pytest.raises(ConfigError, match="metric error: variant steps-1 has no particles/nothere.json"):
        run_study(path)


def test_a_failing_variant_does_not_stop_the_others(toy_config):
    """A variant that fails (a blow-up is a result a sweep of time steps expects) gets its row with the one-line
    reason, the other variants run and are reported, and the study exits 1 naming it (it used to stop at the
    first failure with no report). A metric that raises on one variant is that variant's error the same way."""
    from pipeline import StageFailed

    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("sweep:\n  simulate.steps: [1, 2, 4]",
                                  "mode: zip\nsweep:\n  simulate.steps: [1, 2, 4]\n  simulate.fail: [null, bug, null]"))
    with pytest.raises(StageFailed, match=r"study toy_study: 1 of 3 variant\(s\) failed: variant steps-2_fail-bug: "
                                          r".*RuntimeError: boom") as exc:
        run_study(path)
    assert exc.value.exit_code == 1
    out = toy_config.parent / "out" / "toy_study"
    rows = list(csv.reader(open(out / "study.csv")))
    assert [r[0] for r in rows[1:]] == ["1", "2", "4"]
    assert [r[4] for r in rows[1:]] == ["1.0", "", "0.25"] and rows[2][2] == "" and "RuntimeError: boom" in rows[2][-1]
    assert rows[1][-1] == rows[3][-1] == "" and (out / "error_vs_time.png").is_file()
    assert ran(toy_config, "simulate") == 3  # the failed one ran too, and committed nothing
    r = CliRunner().invoke(main, ["study", str(path), "-q"])
    assert r.exit_code == 1 and r.stderr.count("error:") == 1 and "steps-2_fail-bug" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert ran(toy_config, "simulate") == 4  # the two good variants cached; the failed one tried again

    path.write_text(STUDY.replace("file: particles/stats.json, key: stats.error",
                                  "function: 'toy_stages:error_above', args: {limit: 0.3}"))
    with pytest.raises(StageFailed, match=r"1 of 3 variant\(s\) failed: variant steps-4: metric error "
                                          r"\(toy_stages:error_above\): ValueError: no front") as exc:
        run_study(path)
    rows = list(csv.reader(open(out / "study.csv")))
    assert [r[3] for r in rows[1:]] == ["1.0", "0.5", ""] and rows[3][1] != ""  # its run did cost time


def test_variant_folder_names_are_short_safe_and_unique():
    """A swept list of emitters made a folder name of its str(): too long to create (OSError, after the variant
    had run), with brackets, quotes and spaces in it. Plain numbers and words stay as they were."""
    from pipeline.study import variant_name

    assert variant_name({"fluid.spacing": 0.05, "simulate.use": "sph"}) == "spacing-0.05_use-sph"
    assert variant_name({"simulate.steps": 2, "simulate.fail": None}) == "steps-2_fail-None"
    emitters = [{"box": {"min": [-0.5, -0.25, 0.0], "max": [-0.2, 0.05, 0.4]}, "velocity": [0.0, 0.0, 0.0]}] * 9
    names = [variant_name({"fluid.emitters": e}) for e in (emitters, emitters[:8], "a b", "it's", "x/y", "")]
    assert len(set(names)) == len(names) and names[0] == variant_name({"fluid.emitters": list(emitters)})
    for name in names + [variant_name({f"k{i}.value": "v" * 40 for i in range(9)})]:
        assert len(name) <= 120 and all(c.isalnum() or c in "_.+-" for c in name), name


def test_a_study_sweeping_lists_runs_and_plots(toy_config):
    """The last swept key with list values: the plot grouped by the value itself (TypeError: unhashable type:
    'list', exit 1, no plots) and its folder was named by str() of the list."""
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("sweep:\n  simulate.steps: [1, 2, 4]",
                                  "sweep:\n  simulate.steps: [1, 2]\n  fluid.emitters.0.box.max: [[1, 1, 1], [1, 1, 2]]"))
    results, out = run_study(path)
    assert len(results) == 4 and (out / "error_vs_time.png").stat().st_size > 1000
    assert sorted(p.name for p in (out / "variants").iterdir()) == sorted(r.out.split("/")[-1] for r in results)
    rows = list(csv.reader(open(out / "study.csv")))
    assert [r[1] for r in rows[1:3]] == ["[1, 1, 1]", "[1, 1, 2]"]  # the full value in the report


def test_study_md_tells_the_swept_values_apart(toy_config):
    """study.md printed the swept values to 4 figures: 0.1 and 0.1000001 looked the same."""
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("sweep:\n  simulate.steps: [1, 2, 4]", "sweep:\n  fluid.spacing: [0.1, 0.1000001]"))
    _, out = run_study(path)
    md = (out / "study.md").read_text()
    assert "| 0.1 |" in md and "| 0.1000001 |" in md


FINEST = STUDY.replace("file: particles/stats.json, key: stats.error",
                       "function: 'toy_stages:minus_reference', args: {reference: {%s}}")


def test_the_finest_run_is_this_sweeps_and_dropped_variants_are_removed(toy_config):
    """With 4 dropped from the sweep, the metric read the folder variants/steps-4 an earlier config had left (exit 0,
    distances to a run of other settings). The finest run is looked up among this sweep's variants only, and
    the folders of variants the sweep no longer makes are removed when the pipeline published all they hold."""
    from pipeline import StageFailed

    path = toy_config.parent / "study.yaml"
    path.write_text(FINEST % "steps: 4")
    _, out = run_study(path)
    variants = out / "variants"
    (variants / "mine").mkdir()  # a user's folder, and a user's note inside a published variant: kept
    (variants / "steps-2" / "notes.txt").write_text("keep")
    path.write_text((FINEST % "steps: 4").replace("[1, 2, 4]", "[1, 2]"))
    with pytest.raises(StageFailed, match="2 of 2 variant.*no finest run"):
        run_study(path)
    assert sorted(p.name for p in variants.iterdir()) == ["mine", "steps-1", "steps-2"]
    path.write_text((FINEST % "steps: 4").replace("[1, 2, 4]", "[4]"))
    run_study(path)
    assert sorted(p.name for p in variants.iterdir()) == ["mine", "steps-2", "steps-4"]


RECORDED = '''\
from pipeline.stage import Params, Stage


class Recorded(Stage):
    """A simulate stage keeping its own account of its work over every run of a resumed shot, as the SPH driver
    does in meta.json stats.wall_seconds: here a made-up one."""
    kind, name, version = "simulate", "recorded", "1"
    inputs = ("sdf",)
    outputs = ("particles",)
    reads = ("scene", "fluid")

    class Params(Params):
        steps: int = 3
        time_step: float | None = None  # the error, when given
        wall_seconds: float = 40.0

    def run(self, ctx, inputs, params):
        error = params.time_step if params.time_step is not None else 1.0 / params.steps
        (ctx.out_dir / "stats.json").write_text('{"stats": {"error": %s}}' % error)
        (ctx.out_dir / "meta.json").write_text('{"stats": {"wall_seconds": %s}}' % params.wall_seconds)
'''


@pytest.fixture
def recorded(tmp_path, monkeypatch):
    """The stage above, installed as simulate.recorded."""
    plugin = tmp_path / "recorded_plugin"
    (plugin / "recorded-0.1.dist-info").mkdir(parents=True)
    (plugin / "recorded-0.1.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: recorded\nVersion: 0.1\n")
    (plugin / "recorded-0.1.dist-info" / "entry_points.txt").write_text(
        "[pipeline.stages]\nsimulate.recorded = recorded_stage:Recorded\n")
    (plugin / "recorded_stage.py").write_text(RECORDED)
    monkeypatch.syspath_prepend(str(plugin))


def test_a_resumed_shot_is_charged_its_whole_work(toy_config, recorded):
    """A resumed or extended simulation's cost_seconds covers only the process that finished it (an extended shot
    cost half a fresh one's, a killed and resumed one a tenth). A stage that records its work's wall time over
    every part (simulate: meta.json stats.wall_seconds) is charged that, fresh or resumed alike."""
    path = toy_config.parent / "study.yaml"
    path.write_text(STUDY.replace("[1, 2, 4]", "[1, 2]") + "set: ['stages.simulate.use=recorded']\n")
    results, out = run_study(path)
    assert [r.seconds for r in results] == [40.0, 40.0]
    assert [row[1] for row in csv.reader(open(out / "study.csv"))][1:] == ["40.0", "40.0"]
    results, _ = run_study(path)  # cached: the same account
    assert [r.seconds for r in results] == [40.0, 40.0]


def test_the_finest_run_is_found_by_the_sweeps_key_and_value(toy_config, recorded):
    """finest_variant split the folder name on '_': with a swept key such as time_step nothing matched and every
    variant was compared with itself (0.0 for all, exit 0). It is looked up by the sweep's key and value."""
    from pipeline import StageFailed

    path = toy_config.parent / "study.yaml"
    study = (FINEST % "time_step: 0.25").replace("simulate.steps: [1, 2, 4]", "simulate.time_step: [0.25, 0.5, 1.0]") \
        + "set: ['stages.simulate.use=recorded']\n"
    path.write_text(study)
    results, _ = run_study(path)
    assert [r.metrics["error"] for r in results] == [0.0, 0.25, 0.75]
    # a finest value no variant has: said in each row, never the variant against itself
    path.write_text(study.replace("time_step: 0.25}", "time_step: 0.125}"))
    with pytest.raises(StageFailed, match="3 of 3 variant.*no finest run: no variant of the study has"):
        run_study(path)
