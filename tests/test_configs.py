"""Every runnable config in configs/ runs end to end through the real stages at a tiny size."""
from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
import yaml

import pipeline
from pipeline import Registry

# scene configs (study configs, with study_version, sweep scene configs and are run by their own tests)
CONFIGS = sorted(c for c in (Path(__file__).resolve().parents[1] / "configs").glob("*.yaml")
                 if "config_version" in yaml.safe_load(c.read_text()))


def external_models(raw: dict, config: Path) -> list[Path]:
    """Wall files outside the repository (the gargoyle, whose terms keep it out: ../shared/assets)."""
    files = [config.parent / w["file"] for w in raw.get("walls", []) if "file" in w]
    return [f for f in files if "shared" in f.parts]


@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_config_runs_at_tiny_size(config, tmp_path):
    raw = yaml.safe_load(config.read_text())
    missing = [f for f in external_models(raw, config) if not f.is_file()]
    if missing:
        pytest.skip(f"needs {missing[0]} (not redistributable, read from ../shared/assets beside the repository)")
    spacing = raw["fluid"]["spacing"] * 2.5
    sets = ("scene.frames.count=3", f"fluid.spacing={spacing}")
    if "render" in raw.get("stages", {}):
        sets += ("render.resolution=[160, 90]",)
    report = pipeline.run(config, registry=Registry.from_entry_points(), overrides=sets,
                          cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    assert {s.status for s in report.stages} == {"ran"}
    assert set(report.outputs) == set(raw.get("outputs", ["usd", "frames", "movie"]))
    sim = next(s for s in report.stages if s.kind == "simulate")
    meta = json.loads((Path(report.cache) / "simulate" / sim.key[:2] / sim.key / "meta.json").read_text())
    assert meta["stats"]["particles"] > 0
    assert max(meta["stats"]["inside_wall"]) == 0 and meta["stats"]["left_domain"] == 0
    if "frames" in report.outputs:
        assert len(list(Path(report.outputs["frames"]).glob("*.png"))) == 3


def test_the_readme_config_reference_runs(tmp_path, caplog):
    """The README's annotated config block, saved beside configs/assets as it says, runs to the simulation
    (it named files that did not exist and put its jet above its own tank; then its jet on its own block of
    water, blocked at once, and its sink inside that block)."""
    import logging

    repo = Path(__file__).resolve().parents[1]
    text = (repo / "README.md").read_text().split("## Config reference", 1)[1]
    block = text.split("```yaml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "assets").symlink_to(repo / "configs" / "assets")
    config = tmp_path / "reference.yaml"
    config.write_text(block)
    with caplog.at_level(logging.INFO):
        report = pipeline.run(config, registry=Registry.from_entry_points(),
                              overrides=("scene.frames.count=2", "fluid.spacing=0.05"), until="simulate",
                              cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    assert [s.status for s in report.stages] == ["ran", "ran", "ran"]
    for what in ("start inside a sink", "blocked", "layers were skipped", "can remove nothing", "points into a wall"):
        assert what not in caplog.text, what


def test_what_users_type_is_read_as_they_meant(tmp_path):
    """YAML 1.1 read fps: 030 as 24 (octal), spacing: 1:30 as 90 (base 60) and yes as 1.0; an empty effect
    key turned the effect off; a --set through an alias changed every place sharing it; a merge key with an
    override was refused as a duplicate; a symlinked config read the files beside its target."""
    from pipeline import Registry
    from pipeline.config import load_config

    text = textwrap.dedent("""\
        config_version: 1
        scene: {name: x, frames: {fps: 030, count: 2}}
        fluid:
          spacing: 1e-1
          emitters:
            - box: &b {min: [0, 0, 0], max: [1, 1, 1]}
            - box: *b
              velocity: [1, 0, 0]
        effects:
          gravity:
          viscosity: {mu: 0.01}
        stages:
          simulate:
            <<: {cfl: 0.3, threads: 1}
            cfl: 0.2
        """)
    (tmp_path / "shot").mkdir()
    (tmp_path / "template.yaml").write_text(text)
    (tmp_path / "shot" / "linked.yaml").symlink_to(tmp_path / "template.yaml")
    config = load_config(tmp_path / "shot" / "linked.yaml", Registry.from_entry_points(),
                         ["fluid.emitters.0.box.max=[0.5, 0.5, 0.5]"])
    scene = config.scene
    assert scene.scene.frames.fps == 30 and scene.fluid.spacing == 0.1
    assert scene.effects.gravity is not None and scene.effects.gravity.g == pytest.approx(9.81)
    assert tuple(scene.fluid.emitters[0].box.max) == (0.5, 0.5, 0.5)
    assert tuple(scene.fluid.emitters[1].box.max) == (1.0, 1.0, 1.0)  # the alias's other use is untouched
    assert config.stages["simulate"].params.cfl == 0.2
    assert config.dir == tmp_path / "shot"  # beside the link: its files, its cache and outputs
    from pipeline.config import _Lines, apply_override

    data = {"scene": {"name": "x"}}
    apply_override(data, "scene.name=shot #3", _Lines("t.yaml"))  # a shell argument: no YAML comment in it
    assert data["scene"]["name"] == "shot #3"


def test_a_hex_colour_given_with_set_and_labels_that_stay_readable():
    """`--set render.background=#ffffff` was read as a YAML comment (no value) and the quoted form kept its
    quotes (an invalid colour, found at the first frame after the simulation); labels were white on any
    background, invisible on white."""
    from pipeline.config import _Lines, apply_override
    from stages.render.pyvista_render import RenderParams, text_colour

    for text in ("#ffffff", '"#ffffff"', "'#ffffff'"):
        data = {"stages": {}}
        apply_override(data, f"render.background={text}", _Lines("t.yaml"))
        assert data["stages"]["render"]["background"] == "#ffffff", text
    assert text_colour(RenderParams(background="white")) == "black"
    assert text_colour(RenderParams()) == "white"  # the default dark grey
    with pytest.raises(ValueError, match="is not a colour"):
        RenderParams(background="notacolour")
