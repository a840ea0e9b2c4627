from __future__ import annotations

import os
import textwrap
from pathlib import Path

import pytest

os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")  # as the CLI does: no TBB version warning

TESTS = Path(__file__).parent
REPO = TESTS.parent

TOY_CONFIG = """\
config_version: 1
scene:
  name: toy
  frames: {fps: 10, count: 4}
fluid:
  spacing: 0.1
  emitters:
    - box: {min: [0, 0, 0], max: [1, 1, 1]}
stages:
  mesh_import: {use: toy}
  sdf_bake: {use: toy}
  simulate: {use: toy}
  surface_extract: {use: toy}
  render: {use: toy}
  export: {use: toy}
outputs: [frames]
"""


def no_wall_terms(sdf, h):
    """Walls whose map is empty (no wall term anywhere) over ``sdf``: internal forces only, and the push-out
    (walls.maps.push_out) against the SDF alone."""
    from types import SimpleNamespace

    import numpy as np

    from stages.simulate.walls.maps import make_walls
    empty = SimpleNamespace(index=np.full((1, 1, 1), -1, np.int32), bricks=np.zeros((0, 4, 4, 4, 5), np.float32),
                            shape=np.array([2, 2, 2]), origin=np.zeros(3), spacing=1.0, fix_rho=np.zeros(8), inv_dr=7 / h)
    return make_walls(sdf, empty)


def write_toy_plugin(root: Path) -> Path:
    """A fake installed distribution whose entry points register the toy stages (the real mechanism)."""
    dist = root / "toy_plugin-0.1.dist-info"
    dist.mkdir(parents=True, exist_ok=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(textwrap.dedent("""\
        [pipeline.stages]
        mesh_import.toy = toy_stages:ToyImport
        sdf_bake.toy = toy_stages:ToyBake
        simulate.toy = toy_stages:ToySimulate
        surface_extract.toy = toy_stages:ToySurface
        render.toy = toy_stages:ToyRender
        export.toy = toy_stages:ToyExport
        """))
    return root


@pytest.fixture
def one_numba_thread():
    """numba on one thread for the test: a few hundred to two thousand MPS particles, where the CG's thread
    barriers cost more than a second thread gives."""
    import numba as nb
    before = nb.get_num_threads()
    nb.set_num_threads(1)
    yield
    nb.set_num_threads(before)


@pytest.fixture
def toy_plugin(tmp_path_factory, monkeypatch):
    root = write_toy_plugin(tmp_path_factory.mktemp("plugin"))
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.syspath_prepend(str(TESTS))
    return root


@pytest.fixture
def toy_config(tmp_path, toy_plugin):
    path = tmp_path / "toy.yaml"
    path.write_text(TOY_CONFIG)
    return path


def ran(config: Path, stage: str) -> int:
    """How many times a toy stage really ran for this config."""
    f = config.parent / f"ran_{stage}.log"
    return len(f.read_text().split()) if f.exists() else 0


def spans(config: Path, stage: str) -> list[tuple[float, float]]:
    f = config.parent / f"span_{stage}.log"
    return [tuple(map(float, line.split())) for line in f.read_text().splitlines()] if f.exists() else []
