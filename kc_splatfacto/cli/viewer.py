"""``kc-viewer --load-config RUN/config.yml``: a finished run in the browser (viser).

The training views as camera frustums, the project's render of the browser's camera (or, ticked, the Gaussians as
WebGL splats: what ``kc-export`` writes), and a camera-path editor whose JSON ``kc-render`` reads. Serves until
Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

from kc_splatfacto.cli.main import add_run_arguments, existing_run_config, run_cli
from kc_splatfacto.engine.base_config import ViewerConfig
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.engine.validation import check_ranges
from kc_splatfacto.viewer.viewer import Viewer, import_viser

#: kc-viewer renders a still scene: a larger frame than the training viewer's budget allows
DEFAULT_MAX_RENDER_PIXELS = 800 * 600


def open_viewer(load_config: Path, step: int | None = None, host: str = "127.0.0.1", port: int = 7007,
                max_render_pixels: int = DEFAULT_MAX_RENDER_PIXELS):
    """The :class:`~kc_splatfacto.viewer.viewer.Viewer` of a finished run (serving; call ``serve_forever``)."""
    config = ViewerConfig(enabled=True, host=host, port=port, max_render_pixels=max_render_pixels)
    check_ranges(config)  # the flags' values checked where they enter, before the (slow) run loading
    import_viser()  # the install hint before the (slow) run loading
    loaded = load_run(load_config, step=step, device="cpu")
    test = loaded.test_dataset
    initial = test.cameras[0] if test is not None and len(test) else None
    return Viewer(config, loaded.model, loaded.train_dataset, loaded.run_dir, training=False, initial_camera=initial)


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-viewer``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-viewer", main, argv)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="kc-viewer", description="A trained run in the browser (viser).")
    add_run_arguments(parser)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on ('0.0.0.0' for other machines)")
    parser.add_argument("--port", type=int, default=7007, help="port (the next free one when taken)")
    parser.add_argument("--max-render-pixels", type=int, default=DEFAULT_MAX_RENDER_PIXELS,
                        help="largest frame the rasterizer renders for the browser")
    args = parser.parse_args(argv)
    load_config = existing_run_config("kc-viewer", args.load_config)
    viewer = open_viewer(load_config, args.step, args.host, args.port, args.max_render_pixels)
    print(f"kc-viewer: {viewer.run_dir} at {viewer.url} (Ctrl-C to stop)", flush=True)
    stop = threading.Event()
    try:
        viewer.serve_forever(stop)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
