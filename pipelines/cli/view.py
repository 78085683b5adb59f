"""``narf-view``: look at a fitted avatar in the browser and pose it (docs/guides/viewer.md)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from pipelines.cli.common import (
    HelpFormatter,
    add_motion_fps,
    add_smpl_dir,
    at_least,
    own_context,
    run_cli,
    use_smpl_dir,
)


@own_context
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="narf-view",
        description="Serve a fitted avatar to the browser (viser): the field is rendered for each tab's camera and "
        "streamed as the scene's background with its depth, a low-resolution preview while the camera moves and the "
        "full frame once it rests. Controls: capture-frame slider, --motion playback (play / pause, speed), joint "
        "rotation handles, bone-length sliders, RGB / depth / parts, the training cameras as view presets, a "
        "screenshot (saved under RUN/viewer/screenshots/) and 'save camera path' (RUN/viewer/camera_paths/, for "
        "narf-render-video --camera-path). For an autoencoder run: people of its set to choose (person A, "
        "whose skeleton the poses go on) and blend (towards person B). Ctrl-C stops the server.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--run", type=Path, required=True, help="run folder written by narf-fit --out")
    parser.add_argument("--port", type=at_least(1, 65535), default=8080, help="port of the page")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    parser.add_argument(
        "--motion", type=Path, default=None, help="an AMASS .npz, ZJU params/ folder or SURREAL _info.mat to play"
    )
    add_motion_fps(parser)
    parser.add_argument("--preview", type=at_least(32, 1024), default=192, help="long side of the preview (pixels)")
    parser.add_argument("--full", type=at_least(64, 4096), default=512, help="long side of the still frame (pixels)")
    add_smpl_dir(parser)
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    args = parser.parse_args(argv)
    from fitting.run_folder import auto_device
    from pipelines.runs.kinds import open_run
    from pipelines.runs.requests import a_run

    use_smpl_dir(args.smpl_dir)
    if args.motion_fps is not None and args.motion is None:
        raise ValueError("--motion-fps is the frame rate of a --motion FILE")
    if not args.run.is_dir():
        raise FileNotFoundError(f"{args.run}: no such run folder")
    check_host(args.host)
    kind, run = open_run(args.run)  # a missing or foreign checkpoint fails here, before any server starts
    if kind.name not in ("subject", "autoencoder"):
        raise ValueError(f"{args.run}: {a_run(kind.name)}; narf-view shows subject and autoencoder runs")
    if kind.name == "autoencoder" and args.motion is not None:
        raise ValueError(f"{args.run}: {a_run(kind.name)} plays its people's poses; --motion is for subject runs")
    from narf.fields import model_spec
    from pipelines.viewer.app import Viewer, autoencoder_viewer_data, viewer_data

    device = str(auto_device(args.device))
    if kind.name == "autoencoder":
        data = autoencoder_viewer_data(run, device, args.preview, args.full)
    else:
        data = viewer_data(run, args.motion, device, args.preview, args.full, args.motion_fps)
    if not model_spec(data.config.model.name).rays:
        raise ValueError(f"{args.run}: the CNN baseline renders fixed-size images, not views: nothing to orbit")
    viewer = Viewer(data, args.host, args.port)
    port = viewer.server.get_port()
    if port != args.port:
        print(f"narf-view: port {args.port} is busy; serving on port {port} instead", file=sys.stderr)
    print(f"narf-view: serving {args.run} at http://{args.host}:{port} (Ctrl-C stops it)")
    try:
        while True:
            time.sleep(3600)
    finally:
        viewer.stop()


def check_host(host: str, timeout: float = 5.0) -> None:
    """Refuse, within ``timeout`` seconds, a ``--host`` that does not resolve or is not an address of this machine
    (the server would otherwise wait for it for ever)."""
    import concurrent.futures
    import socket

    pool = concurrent.futures.ThreadPoolExecutor(1)
    try:
        infos = pool.submit(socket.getaddrinfo, host, None, type=socket.SOCK_STREAM).result(timeout=timeout)
    except (OSError, concurrent.futures.TimeoutError) as err:
        raise ValueError(f"--host {host}: the name does not resolve ({err or 'timed out'})") from None
    finally:
        pool.shutdown(wait=False)
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((address[0], 0))
        except OSError as err:
            raise ValueError(f"--host {host}: not an address of this machine ({err.strerror})") from None


def entrypoint() -> None:
    sys.exit(run_cli("narf-view", main))
