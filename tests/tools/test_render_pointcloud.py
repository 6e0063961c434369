import matplotlib
import numpy as np
import torch

from dapm_lightning.geometry import ideal_ground_depth
from dapm_lightning.tools.predict import make_prediction
from dapm_lightning.tools.render_pointcloud import render


def test_render_writes_a_figure_without_touching_global_matplotlib_state(tmp_path):
    backend, params = matplotlib.get_backend(), dict(matplotlib.rcParams)
    import matplotlib.pyplot as plt

    figures = plt.get_fignums()
    pose = torch.tensor([40.0, -30.0, 10.0, 80.0])
    prediction = make_prediction("x", (24, 32), ideal_ground_depth(pose[None], (24, 32))[0], None, pose)
    rgb = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    out = render(rgb, prediction, tmp_path / "view.png", stride=2)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert matplotlib.get_backend() == backend and dict(matplotlib.rcParams) == params
    assert plt.get_fignums() == figures
