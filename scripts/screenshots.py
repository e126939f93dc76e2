"""Screenshots of every Rerun view as a user sees it, to look at before calling a view done.

    uv run python scripts/screenshots.py                  # a tiny pipeline run in a temp folder
    uv run python scripts/screenshots.py --data data --out /tmp/shots   # an existing run

Dark theme: the native viewer, headless (`rerun.experimental.ViewerClient`, software Vulkan:
`apt-get install mesa-vulkan-drivers`), at the recording's default time and at chosen times.
Light theme: the web viewer (`rerun --web-viewer`) in headless Chromium driven by chromedriver
over plain WebDriver HTTP (`apt-get install chromium chromium-driver`); skipped without them.
Pictures go to --out (not into the repository).
"""

from __future__ import annotations

import argparse
import base64
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
TINY = {  # small and quick, but enough training that paths look like something
    "ingest": {"episodes": 40, "episode_steps": 600},
    "segment": {"window": 20},
    "train": {"z_dim": 8, "hidden": 64, "max_steps": 400, "eval_every": 200, "val_windows": 200},
    "dynamics": {"hidden": 32, "max_steps": 500, "eval_every": 250, "val_transitions": 500},
    "validate": {"starts": 8, "skills": 4, "repeats": 4, "particles": 16, "record_starts": 4},
    "deploy": {"agents": ["oposm", "expert"], "episodes": 8, "num_envs": 8, "max_steps": 400,
               "record_episodes": 3},
    "planner": {"horizon": 5, "candidates": 32, "elites": 8, "iterations": 5},
}  # fmt: skip


def tiny_run(folder: Path) -> Path:
    """Run ingest .. deploy on tiny params into `folder/data`; return the data root."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    for section, values in TINY.items():
        if section != "planner":
            params[section].update(values)
    params["deploy"]["planner"].update(TINY["planner"])
    (folder / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    data = folder / "data"
    for stage in ("ingest", "segment", "train", "dynamics", "validate", "deploy"):
        print(f"oposm {stage} (tiny)", flush=True)
        oposm = Path(sys.executable).parent / "oposm"
        command = [oposm, stage, "-p", folder / "params.yaml", "--data", data]
        subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
    return data


def pick_episodes(data: Path) -> list[Path]:
    """One recorded success and one recorded failure per agent (where there are)."""
    rows = json.loads((data / "reports/deploy/episodes.json").read_text())
    folder = data / "recordings/deploy"
    chosen: dict[tuple[str, bool], Path] = {}
    for r in rows:
        name = f"{r['task']}-{r['episode']:04d}.rrd"
        path = folder / (f"{r['agent']}-{name}" if r.get("agent") else name)
        if path.exists():
            chosen.setdefault((r.get("agent", ""), r["success"]), path)
    return list(chosen.values())


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(port: int, timeout: float = 60.0) -> None:
    """Until something listens on `port` (the web viewer starts in seconds on a busy machine)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def dark(shots: list[tuple[Path, str, dict]], out: Path) -> None:
    """Native viewer, headless: `(recording, name, time)` with time {} (the default), or
    {"timeline": ..., "sequence" | "duration": ...}."""
    from rerun.experimental import ViewerClient

    viewer = ViewerClient.spawn(headless=True, port=free_port(), hide_welcome_screen=True)
    try:
        time.sleep(8)  # start-up notifications fade
        for path, name, at in shots:
            viewer.open(str(path))
            time.sleep(2)
            if at:
                viewer.set_time(at.pop("timeline"), play_state="paused", **at)
                time.sleep(1)
            viewer.save_screenshot(str(out / f"dark-{name}.png"))
            print(out / f"dark-{name}.png", flush=True)
    finally:
        viewer.quit()


def _webdriver(method: str, url: str, body: dict | None = None) -> dict:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(
        url, data=data, method=method, headers={"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(request, timeout=120) as response:
        return json.loads(response.read())["value"]


def light(shots: list[tuple[Path, str]], out: Path, size: str = "1600,900") -> None:
    """Web viewer in headless Chromium (SwiftShader), light theme, at the default time; a fresh
    browser per picture (a busy software-rendered page does not navigate away in time)."""
    if not (shutil.which("chromedriver") and shutil.which("chromium")):
        print("light theme skipped: apt-get install chromium chromium-driver", flush=True)
        return
    driver_port = free_port()
    driver = subprocess.Popen(
        ["chromedriver", f"--port={driver_port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{driver_port}"
    flags = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--hide-scrollbars",
             "--enable-unsafe-swiftshader", f"--window-size={size}"]  # fmt: skip
    options = {"binary": shutil.which("chromium"), "args": flags}
    caps = {"capabilities": {"alwaysMatch": {"goog:chromeOptions": options}}}
    try:
        time.sleep(1)
        for path, name in shots:
            web_port, grpc_port = free_port(), free_port()
            server = subprocess.Popen(
                [sys.executable, "-m", "rerun", "--web-viewer", "--web-viewer-port",
                 str(web_port), "--port", str(grpc_port), str(path)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            page = f"{base}/session/{_webdriver('POST', f'{base}/session', caps)['sessionId']}"
            try:
                wait_for(web_port)
                source = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
                url = f"http://127.0.0.1:{web_port}/?url={source}&theme=light"
                _webdriver("POST", f"{page}/url", {"url": url})
                for wait in (15, 30):  # the wasm viewer loads and renders on a software GPU
                    time.sleep(wait)
                    try:
                        png = base64.b64decode(_webdriver("GET", f"{page}/screenshot"))
                    except urllib.error.HTTPError as exc:  # the renderer was too busy to answer
                        print(f"light-{name}: {exc.read()[:200]!r}", flush=True)
                        continue
                    (out / f"light-{name}.png").write_bytes(png)
                    print(out / f"light-{name}.png", flush=True)
                    break
            finally:
                _webdriver("DELETE", page)
                server.terminate()
                server.wait()
    finally:
        driver.terminate()
        driver.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="a run's data root (default: a tiny run)")
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "oposm-shots")
    parser.add_argument("--no-light", action="store_true", help="skip the web viewer")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    data = args.data or tiny_run(Path(tempfile.mkdtemp(prefix="oposm-shots-run-")))

    from pipeline.viz.dataset import write_dataset_view

    demos = sorted((data / "demos").glob("*.mcap"))
    dataset = args.out / "dataset.rrd"
    if demos:
        write_dataset_view(demos[0], dataset)
    deploy = data / "recordings/deploy"
    validate = data / "recordings/validate.rrd"
    episodes = pick_episodes(data)
    mid = [{"timeline": "step", "sequence": 90}, {"timeline": "step", "sequence": 25}]
    shots = [(deploy / "overview.rrd", "overview", {})]
    for path in episodes:
        shots += [(path, path.stem, {}), (path, f"{path.stem}-step90", dict(mid[0]))]
    shots += [(validate, "validate", {}), (validate, "validate-step25", dict(mid[1]))]
    if demos:
        shots.append((dataset, "dataset", {"timeline": "time", "duration": 30.0}))
    shots = [s for s in shots if s[0].exists()]
    dark(shots, args.out)
    if not args.no_light:
        light([(p, n) for p, n, at in shots if not at], args.out)


if __name__ == "__main__":
    main()
