"""Screenshots of a recording as a person sees it: Rerun's web viewer in headless Chromium.

    python docs/screenshots/make_screenshots.py examples/out/recording.rrd --out /tmp/shots

serves the recording with ``rerun --serve-web`` (the viewer that ships with rerun-sdk), opens it
in headless Chromium (WebGL on SwiftShader, no GPU or display needed), and saves one PNG per tab
of the recording's blueprint (``00_Summary.png``, ``01_<stage>.png``...). Each tab is shown by
re-sending the recording's own blueprint with that tab active, so what is captured is what a
person sees after clicking the tab. A screenshot is taken once three consecutive frames agree
and differ from the tab before in more than 2 % of the pixels (the viewer has drawn the tab
sent), or after ``--wait`` seconds. On a loaded machine a viewer still reading the file redraws
as it goes: look at each PNG's active tab (a PNG may show the tab before it).

``report.html`` is captured with ``--html out/report.html``: a full-page screenshot
(``report.png``), one per section (``report_00_Summary.png``, ``report_01_<stage>.png``...) and
one per figure (``report_01_fig00.png``..., zoomed ``--figure-scale``), to look at closely.

The README's image is made from the demo's recording (``bash examples/demo.sh`` first) with

    python docs/screenshots/make_screenshots.py examples/out/recording.rrd --hero allan --collapse-panels

which writes ``docs/images/recording_allan.png`` (the tab whose name holds ``allan``) and
``docs/images/recording_allan.json``: the views the tab shows and the stage's figures as the
summary gives them. ``tests/test_one_record.py`` (slow) runs the demo and fails when either has
drifted from what the current code shows: then run the two commands above again.

Needs: ``chromium`` (Debian's package) on PATH, and the ``rerun`` viewer binary (rerun-sdk).
Look at every screenshot before calling a view done.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--hide-scrollbars",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def browser() -> str | None:
    """The Chromium executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    return None


def rerun_binary() -> str | None:
    """The ``rerun`` viewer binary shipped with rerun-sdk, else the one on PATH."""
    try:
        import rerun_cli  # type: ignore[import-not-found]

        path = Path(rerun_cli.__file__).parent / "rerun"
        if path.exists():
            return str(path)
    except ImportError:
        pass
    return shutil.which("rerun")


@contextlib.contextmanager
def process(args: list[str], **kwargs) -> Iterator[subprocess.Popen]:
    """A child process in its own process group, ended (by its id) on exit."""
    proc = subprocess.Popen(
        args,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        **kwargs,
    )
    try:
        yield proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def wait_http(url: str, timeout: float = 30.0) -> bytes:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as resp:
                return resp.read()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class Page:
    """One Chromium tab driven over the DevTools protocol (aiohttp's websocket client)."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.n = 0

    async def call(self, method: str, **params):
        self.n += 1
        await self.ws.send_json({"id": self.n, "method": method, "params": params})
        while True:
            msg = await self.ws.receive_json()
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    async def screenshot(self, full_page: bool = False) -> bytes:
        params = {"format": "png"}
        if full_page:
            params["captureBeyondViewport"] = True
        return base64.b64decode((await self.call("Page.captureScreenshot", **params))["data"])

    async def settled(
        self, wait: float, before: bytes = b"", interval: float = 2.0, agree: int = 3
    ) -> bytes:
        """A screenshot once it differs from ``before`` and ``agree`` consecutive ones agree (or
        after ``wait`` seconds). Three, not two: a re-sent blueprint shows its first tab for a
        moment before the active one (on a loaded machine, for two frames)."""
        deadline = time.monotonic() + wait
        same, last = 0, b""
        while True:
            await asyncio.sleep(interval)
            shot = await self.screenshot()
            same = same + 1 if shot == last else 1
            if (same >= agree and changed(shot, before)) or time.monotonic() > deadline:
                return shot
            last = shot


def changed(shot: bytes, before: bytes, share: float = 0.02) -> bool:
    """Whether ``shot`` differs from ``before`` in more than ``share`` of its pixels, each by
    more than a shade (another tab drawn), not only in a few (a notification dot: on a loaded machine the viewer took
    longer than three frames to show the tab sent, and each PNG showed the tab before it)."""
    if not before:
        return True
    import io

    import numpy as np
    from PIL import Image

    a, b = (np.asarray(Image.open(io.BytesIO(x)).convert("RGB")) for x in (shot, before))
    if a.shape != b.shape:
        return True
    # by more than a shade: a 3D view drawn again differs in many pixels by a few levels
    differ = np.any(np.abs(a.astype(np.int16) - b.astype(np.int16)) > 48, axis=2)
    return float(differ.mean()) > share


@contextlib.asynccontextmanager
async def chromium(width: int, height: int):
    import aiohttp

    port = free_port()
    exe = browser()
    if exe is None:
        sys.exit("no chromium on PATH (Debian: apt-get install chromium)")
    with (
        tempfile.TemporaryDirectory() as profile,
        process(
            [
                exe,
                *CHROMIUM_FLAGS,
                f"--user-data-dir={profile}",
                f"--window-size={width},{height}",
                f"--remote-debugging-port={port}",
                "about:blank",
            ]
        ),
    ):
        tabs = json.loads(wait_http(f"http://127.0.0.1:{port}/json"))
        ws_url = next(t for t in tabs if t["type"] == "page")["webSocketDebuggerUrl"]
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(ws_url, max_msg_size=0) as ws,
        ):
            page = Page(ws)
            await page.call("Page.enable")
            await page.call(
                "Emulation.setDeviceMetricsOverride",
                width=width,
                height=height,
                deviceScaleFactor=1,
                mobile=False,
            )
            yield page


# -- the recording's blueprint, one tab at a time ----------------------------------------------
TABS = 1  # ContainerKind.Tabs


class Blueprint:
    """The blueprint stored in a recording: its chunks and its containers' fields."""

    def __init__(self, rrd: Path) -> None:
        import rerun.chunk as rc

        reader = rc.RrdReader(str(rrd))
        stores = reader.blueprints()
        if not stores:
            sys.exit(f"{rrd}: no blueprint in the recording")
        self.app_id = stores[0].application_id
        self.chunks = list(reader.stream(store=stores[0]).to_chunks())
        root = self.field("/viewport", "ViewportBlueprint:root_container")
        self.root = f"/container/{_uuid(root)}"

    def field(self, path: str, column: str):
        """The last value of a blueprint component (None when absent)."""
        import pyarrow as pa

        value = None
        for chunk in self.chunks:
            if chunk.entity_path == path:
                batch = chunk.to_record_batch()
                if column in batch.schema.names:
                    value = pa.array(batch.column(column)).to_pylist()[-1]
        return value[0] if isinstance(value, list) and len(value) == 1 else value

    def contents(self, container: str) -> list[str]:
        entries = self.field(container, "ContainerBlueprint:contents") or []
        if isinstance(entries, (str, bytes)):  # a container of one: field() unwrapped it
            entries = [entries]
        return ["/" + str(e).lstrip("/") for e in entries]

    def name(self, path: str) -> str:
        kind = "ContainerBlueprint" if path.startswith("/container") else "ViewBlueprint"
        return str(self.field(path, f"{kind}:display_name") or path.rsplit("/", 1)[-1])

    def inner_tabs(self, path: str) -> list[str]:
        """The tab containers inside ``path`` (depth first)."""
        if not path.startswith("/container"):
            return []
        found = [path] if self.field(path, "ContainerBlueprint:container_kind") == TABS else []
        for child in self.contents(path):
            found += self.inner_tabs(child)
        return found

    def shots(self) -> list[tuple[str, dict[str, str]]]:
        """(file name, {tab container: active tab}) for every tab, inner tabs included."""
        out = []
        for i, tab in enumerate(self.contents(self.root)):
            inner = self.inner_tabs(tab)
            if not inner:
                out.append((f"{i:02d}_{safe(self.name(tab))}", {self.root: tab}))
            for container in inner:
                for j, sub in enumerate(self.contents(container)):
                    name = f"{i:02d}{chr(ord('a') + j)}_{safe(self.name(sub))}"
                    out.append((name, {self.root: tab, container: sub}))
        return out


def _uuid(value) -> str:
    """A blueprint UUID (16 bytes, possibly wrapped in a list or struct) as text."""
    import uuid

    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if isinstance(value, dict):
        value = next(iter(value.values()))
    return str(uuid.UUID(bytes=bytes(value)))


def send_tabs(url: str, bp: Blueprint, active: dict[str, str], collapse: bool) -> None:
    """Send the recording's blueprint to the viewer at ``url`` with the ``active`` tabs."""
    import rerun as rr
    import rerun.blueprint as rrb
    import rerun_bindings as bindings
    from rerun.blueprint.archetypes import ContainerBlueprint, PanelBlueprint

    stream = rr.RecordingStream._from_native(
        bindings.new_blueprint(
            application_id=bp.app_id,
            make_default=False,
            make_thread_default=False,
            default_enabled=True,
        )
    )
    stream.send_chunks(bp.chunks)
    stream.set_time("blueprint", sequence=2**62)
    for container, tab in active.items():
        stream.log(container, ContainerBlueprint.from_fields(active_tab=tab.lstrip("/")))
    if collapse:
        for panel in ("blueprint_panel", "selection_panel"):
            stream.log(panel, PanelBlueprint(state=rrb.PanelState.Collapsed))
    bindings.connect_grpc_blueprint(url, True, False, stream.to_native())


def tab_views(bp: Blueprint, path: str) -> list[str]:
    """The names of the views inside a tab or container (depth first)."""
    if not path.startswith("/container"):
        return [bp.name(path)]
    return [v for child in bp.contents(path) for v in tab_views(bp, child)]


def hero_record(rrd: Path, stage: str) -> dict:
    """What the README's image of ``stage``'s tab shows: the tab's views and the stage's rows
    (the summary's quantities and cells, from ``calibration.json`` beside the recording)."""
    from imupipe.pipeline.report.summary import summarise

    bp = Blueprint(rrd)
    tab = next(t for t in bp.contents(bp.root) if bp.name(t) == stage)
    doc = json.loads((rrd.parent / "calibration.json").read_text())
    (summary,) = [s for s in summarise(doc["results"]) if s.name == stage]
    return {
        "made_by": "docs/screenshots/make_screenshots.py --hero " + stage,
        "from": "examples/demo.sh",
        "stage": stage,
        "status": summary.status,
        "views": tab_views(bp, tab),
        "rows": [[r.label, *r.cells] for r in summary.rows],
    }


def safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name).strip("_")


async def shoot_recording(args) -> list[Path]:
    viewer = rerun_binary()
    if viewer is None:
        sys.exit("no rerun viewer binary (pip install rerun-sdk)")
    bp = Blueprint(args.rrd)
    shots = bp.shots()
    if args.tabs:
        shots = [s for s in shots if any(t in s[0] for t in args.tabs)]
    web, grpc = free_port(), free_port()
    proxy = f"rerun+http://127.0.0.1:{grpc}/proxy"
    out: list[Path] = []
    command = [viewer, "--serve-web", "--web-viewer-port", str(web), "--port", str(grpc)]
    with process([*command, str(args.rrd)], env={**os.environ, "RERUN_APP_ONLY": "true"}):
        wait_http(f"http://127.0.0.1:{web}/")
        query = urllib.parse.urlencode({"url": proxy, "renderer": "webgl"})
        async with chromium(args.width, args.height) as page:
            await page.call("Page.navigate", url=f"http://127.0.0.1:{web}/?{query}")
            png = await page.settled(args.wait, agree=5)  # the recording loaded and drawn
            first = {bp.root: bp.contents(bp.root)[0]}  # the tab it opens on, drawn: the
            send_tabs(proxy, bp, first, args.collapse_panels)  # page each tab must differ from
            png = await page.settled(args.wait, before=png)
            for name, active in shots:
                send_tabs(proxy, bp, active, args.collapse_panels)
                png = await page.settled(args.wait, before=b"" if active == first else png)
                target = args.out / f"{name}.png"
                target.write_bytes(png)
                out.append(target)
                print(target)
    return out


async def shoot_html(args) -> Path:
    async with chromium(args.width, args.height) as page:
        await page.call("Page.navigate", url=Path(args.html).resolve().as_uri())
        await asyncio.sleep(2)
        metrics = await page.call("Page.getLayoutMetrics")
        height = int(metrics["cssContentSize"]["height"])
        await page.call(
            "Emulation.setDeviceMetricsOverride",
            width=args.width,
            height=min(height, 30000),
            deviceScaleFactor=1,
            mobile=False,
        )
        png = await page.screenshot()
        target = args.out / "report.png"
        target.write_bytes(png)
        print(target)
        # one PNG per section (the summary, each stage) and per figure, to look at closely
        found = await page.call("Runtime.evaluate", expression=SECTIONS_JS, returnByValue=True)
        for name, box in found["result"]["value"]:
            clip = {**box, "scale": args.figure_scale if "_fig" in name else 1}
            shot = await page.call(
                "Page.captureScreenshot", format="png", clip=clip, captureBeyondViewport=True
            )
            part = args.out / f"report_{safe(name)}.png"
            part.write_bytes(base64.b64decode(shot["data"]))
            print(part)
    return target


SECTIONS_JS = """
(() => {
  const out = [], top = el => el.getBoundingClientRect().top + window.scrollY;
  const heads = [...document.querySelectorAll('h2')];
  heads.forEach((h, i) => {
    const y0 = top(h), y1 = i + 1 < heads.length ? top(heads[i + 1]) : document.body.scrollHeight;
    const n = String(i).padStart(2, '0');
    out.push([n + '_' + (h.id || h.textContent).replace(/^stage-/, ''),
              {x: 0, y: y0 - 4, width: document.body.scrollWidth, height: y1 - y0}]);
    let k = 0, el = h.nextElementSibling;
    while (el && el.tagName !== 'H2') {
      for (const f of el.querySelectorAll('figure')) {
        const r = f.getBoundingClientRect();
        out.push([n + '_fig' + String(k++).padStart(2, '0'),
                  {x: r.left, y: r.top + window.scrollY, width: r.width, height: r.height}]);
      }
      el = el.nextElementSibling;
    }
  });
  return out;
})()
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rrd", type=Path, nargs="?", help="the recording (recording.rrd)")
    p.add_argument("--html", type=Path, help="also capture this HTML report (full page)")
    p.add_argument("--out", type=Path, default=Path("screenshots"), help="folder for the PNGs")
    p.add_argument("--tabs", nargs="*", help="only the tabs whose names contain one of these")
    p.add_argument("--width", type=int, default=1600)
    p.add_argument(
        "--figure-scale", type=float, default=1.5, help="zoom of the report's per-figure PNGs"
    )
    p.add_argument("--height", type=int, default=1000)
    p.add_argument("--wait", type=float, default=40.0, help="longest wait per screenshot (s)")
    p.add_argument(
        "--collapse-panels", action="store_true", help="hide the blueprint and selection panels"
    )
    p.add_argument(
        "--hero",
        metavar="STAGE",
        help="make the README's image of this stage's tab: docs/images/recording_STAGE.png/.json",
    )
    args = p.parse_args(argv)
    if args.hero:
        images = Path(__file__).resolve().parents[1] / "images"
        args.out, args.tabs = Path(tempfile.mkdtemp()), [args.hero]
        shots = asyncio.run(shoot_recording(args))
        shot = next(s for s in shots if s.name.split("_", 1)[1].startswith(safe(args.hero)))
        from PIL import Image  # a palette PNG: a third of the size, the same to the eye

        with Image.open(shot) as im:
            im.convert("RGB").quantize(256).save(
                images / f"recording_{args.hero}.png", optimize=True
            )
        record = hero_record(args.rrd, args.hero)
        text = json.dumps(record, indent=1) + "\n"
        (images / f"recording_{args.hero}.json").write_text(text, encoding="utf-8")
        print(images / f"recording_{args.hero}.png")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    if args.rrd:
        asyncio.run(shoot_recording(args))
    if args.html:
        asyncio.run(shoot_html(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
