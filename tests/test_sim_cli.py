"""CLI: render to PNG, episode to GIF, reference table, bench; clear errors."""
import imageio.v2 as imageio
import numpy as np

from bimacppo_sim import Scenario, World, load_map
from bimacppo_sim.cli import bench, main, reference_table
from bimacppo_sim.render import Renderer, render_rgb


def test_render_png_and_rgb(tmp_path):
    out = tmp_path / "s.png"
    assert main(["render", "--map", "dual_lane_4way", "--n-sv", "3", "--task", "left", "--seed", "1",
                 "-o", str(out)]) == 0
    img = imageio.imread(out)
    assert img.ndim == 3 and img.shape[0] > 100
    w = World(load_map("single_lane_4way"))
    w.reset(Scenario(2, "straight", 0))
    a = render_rgb(w, x_imr=[1.75, -5.0, 1.57])
    b = render_rgb(w)
    assert a.dtype == np.uint8 and a.shape[2] == 3 and a.shape == b.shape
    assert not np.array_equal(a, b)           # the x_IMR marker is drawn
    r = Renderer(w)
    f1 = r.rgb_array()
    w.step([3.0, 0.0])
    for _ in range(10):
        w.step([3.0, 0.0])
    f2 = r.rgb_array()
    r.close()
    assert not np.array_equal(f1, f2)         # vehicles moved


def test_episode_gif(tmp_path):
    out = tmp_path / "e.gif"
    assert main(["episode", "--driver", "yield", "--n-sv", "1", "--task", "right", "--seed", "2",
                 "--every", "10", "-o", str(out)]) == 0
    frames = imageio.mimread(out)
    assert len(frames) >= 3
    from PIL import Image
    assert Image.open(out).info["duration"] == round(1000 * World(load_map("dual_lane_4way")).dt * 10)  # ms


def test_cli_errors_are_clear(capsys):
    assert main(["render", "--map", "nowhere", "-o", "/tmp/x.png"]) == 2
    assert "unknown map id" in capsys.readouterr().err
    assert main(["render", "--n-sv", "4"]) == 2
    assert "max_sv" in capsys.readouterr().err


def test_reference_and_bench_small():
    rows = reference_table("single_lane_4way", 2, 0, drivers=("go",), progress=False)
    assert len(rows) == 3 * 4
    for d, t, n, s, c, to, mt in rows:
        assert s + c + to == 2 and mt > 0
    r = bench(steps=300)
    assert r["steps"] == 300 and r["steps_per_s"] > 0 and r["tracemalloc_peak_kib"] > 0
