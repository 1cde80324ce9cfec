"""save_figure: a decodable PNG of the figure's size, the figure closed, no temp file left."""

import cv2
import numpy as np

from kc_splatfacto.analysis.figures import pyplot, save_figure


def test_save_figure_writes_a_png_and_closes_the_figure(tmp_path):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot([0, 1], [1, 0])
    path = save_figure(fig, tmp_path / "plots" / "curve.png", dpi=50)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[:2] == (150, 200)  # 3x4 in at 50 dpi
    assert np.unique(image.reshape(-1, 3), axis=0).shape[0] > 2  # something was drawn
    assert fig.number not in plt.get_fignums()
    assert sorted(p.name for p in path.parent.iterdir()) == ["curve.png"]
