"""Screenshot of a rerun recording in the real viewer, at a set time (docs/img/recording_*.png).

Starts rerun's viewer headless (it needs a Vulkan driver: on Debian, ``apt-get install
mesa-vulkan-drivers`` gives the software one), opens the ``.rrd``, pauses it at TIME on
the timeline and saves what the viewer draws:

    heml-gym rollout --policy scripted --env heml_gym/TissueRetraction-v1 --episodes 2 --rrd /tmp/flap.rrd
    python scripts/recording_screenshot.py /tmp/flap.rrd docs/img/recording_tissue.png --time 3.5
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", help="the recording")
    ap.add_argument("out", help="the PNG to write")
    ap.add_argument("--time", type=float, required=True, help="where to pause: seconds (a *_time timeline) or a "
                    "sequence number")
    ap.add_argument("--timeline", default="sim_time")
    ap.add_argument("--size", default="1280x800", help="window size, WxH pixels")
    ap.add_argument("--port", type=int, default=9891)
    args = ap.parse_args(argv)
    if not Path(args.rrd).is_file():
        ap.error(f"rrd: no such file: {args.rrd}")
    from rerun.experimental import ViewerClient

    from heml_gym.envs.render_scene import viewer_executable

    exe = viewer_executable()
    if exe is None:
        ap.error("the rerun viewer is not installed (pip install rerun-sdk)")
    log = tempfile.NamedTemporaryFile("w", suffix=".log", delete=False)
    # the viewer binary itself: terminating the venv's `rerun` wrapper would leave it running
    viewer = subprocess.Popen([exe, "--headless", "--window-size", args.size, "--port", str(args.port),
                               "--hide-welcome-screen"], stdout=log, stderr=subprocess.STDOUT)
    try:
        for _ in range(120):
            try:
                client = ViewerClient.connect(f"rerun+http://127.0.0.1:{args.port}/proxy")
                client.get_state()
                break
            except Exception as exc:  # noqa: BLE001 - not listening yet
                error = exc
                time.sleep(1)
        else:
            print(f"the viewer did not start ({error}); its log: {log.name}", file=sys.stderr)
            return 1
        client.open(os.path.abspath(args.rrd))
        time.sleep(3)
        if args.timeline.endswith("time"):
            client.set_time(args.timeline, duration=args.time, play_state="paused")
        else:
            client.set_time(args.timeline, sequence=int(args.time), play_state="paused")
        time.sleep(3)
        for _ in range(2):  # the second, once everything is drawn
            client.save_screenshot(os.path.abspath(args.out))
            time.sleep(1)
        print(f"written: {args.out}")
        return 0
    finally:
        viewer.terminate()
        viewer.wait(timeout=20)


if __name__ == "__main__":
    raise SystemExit(main())
