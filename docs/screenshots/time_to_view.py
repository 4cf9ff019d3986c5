"""How long a recording takes to show in Rerun's web viewer, loaded the ways a person loads it.

    python docs/screenshots/time_to_view.py examples/out/recording.rrd --out /tmp/ttv

opens the recording in headless Chromium (as :mod:`make_screenshots` does) in each ``--mode``:

- ``proxy``: ``rerun --serve-web RECORDING`` (what ``rerun --web-viewer RECORDING`` runs, less
  the browser it opens): the viewer reads the file and streams it to the page over gRPC;
- ``url``: the web viewer (``rerun --serve-web`` without a file) opened with
  ``?url=http://.../recording.rrd``, the file served over plain HTTP: the page fetches the file
  itself (what ``rerun --web-viewer`` does with a URL, and what a shared link does).

It takes a screenshot every second and prints, per mode, the seconds from opening the page to
the first screenshot that differs from the empty viewer and to the first one equal to the final
(settled: ``--settle`` seconds unchanged) view, and saves that final view as ``<mode>.png``: look
at it to see which layout opened (imupipe's tabs, Rerun's automatic layout, or a viewer still
loading: then raise ``--settle``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import http.server
import os
import sys
import threading
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from make_screenshots import chromium, free_port, process, rerun_binary, wait_http  # noqa: E402


class CorsHandler(http.server.SimpleHTTPRequestHandler):
    """A static file server whose files a page on another port may fetch."""

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, *args) -> None:
        pass


@contextlib.contextmanager
def file_server(folder: Path) -> Iterator[int]:
    port = free_port()
    handler = functools.partial(CorsHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield port
    finally:
        server.shutdown()


def viewport(png: bytes) -> bytes:
    """The pixels of the views only: without the top bar and the time panel, whose time cursor
    moves while the recording plays."""
    import io

    from PIL import Image

    with Image.open(io.BytesIO(png)) as im:
        return im.crop((0, 40, im.width, im.height - 60)).tobytes()


async def watch(page, url: str, limit: float, settle: int = 5) -> tuple[float, float, bytes]:
    """(seconds to the first change, seconds to the final view, the final view's PNG)."""
    start = time.monotonic()
    await page.call("Page.navigate", url=url)
    shots: list[tuple[float, bytes, bytes]] = []
    while time.monotonic() - start < limit:
        await asyncio.sleep(1.0)
        png = await page.screenshot()
        shots.append((time.monotonic() - start, viewport(png), png))
        tail = [v for _, v, _ in shots[-settle:]]
        if len(tail) == settle and len(set(tail)) == 1 and len({v for _, v, _ in shots}) > 1:
            break
    final, first = shots[-1][1], shots[0][1]
    changed = next((t for t, v, _ in shots if v != first), float("nan"))
    reached = next(t for t, v, _ in shots if v == final)
    return changed, reached, shots[-1][2]


async def run(args) -> None:
    viewer = rerun_binary()
    if viewer is None:
        sys.exit("no rerun viewer binary (pip install rerun-sdk)")
    rrd = args.rrd.resolve()
    env = {**os.environ, "RERUN_APP_ONLY": "true"}
    for mode in args.mode:
        web, grpc = free_port(), free_port()
        command = [viewer, "--serve-web", "--web-viewer-port", str(web), "--port", str(grpc)]
        with contextlib.ExitStack() as stack:
            if mode == "proxy":
                stack.enter_context(process([*command, str(rrd)], env=env))
                source = f"rerun+http://127.0.0.1:{grpc}/proxy"
            else:
                stack.enter_context(process(command, env=env))
                port = stack.enter_context(file_server(rrd.parent))
                source = f"http://127.0.0.1:{port}/{urllib.parse.quote(rrd.name)}"
            wait_http(f"http://127.0.0.1:{web}/")
            query = urllib.parse.urlencode({"url": source, "renderer": "webgl"})
            async with chromium(args.width, args.height) as page:
                changed, reached, png = await watch(
                    page, f"http://127.0.0.1:{web}/?{query}", args.limit, args.settle
                )
        target = args.out / f"{mode}.png"
        target.write_bytes(png)
        print(
            f"{mode}: {rrd.name} ({rrd.stat().st_size / 1e6:.1f} MB): first change "
            f"{changed:.0f} s, final view {reached:.0f} s -> {target}",
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rrd", type=Path, help="the recording (recording.rrd)")
    p.add_argument("--out", type=Path, default=Path("time_to_view"), help="folder for the PNGs")
    p.add_argument("--mode", nargs="*", default=["proxy", "url"], choices=["proxy", "url"])
    p.add_argument("--limit", type=float, default=300.0, help="longest wait per mode (s)")
    p.add_argument(
        "--settle",
        type=int,
        default=30,
        help="seconds the view must stay the same to count as final (the viewer can sit still "
        "on a loading state for 10 s and more)",
    )
    p.add_argument("--width", type=int, default=1600)
    p.add_argument("--height", type=int, default=1000)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    asyncio.run(run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
