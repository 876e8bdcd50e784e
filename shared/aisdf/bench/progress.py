"""A progress bar for the interactive benchmark: tqdm when installed, else a plain one
on stderr (redrawn at most twice a second)."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, total: int, enabled: bool = True, stream=None):
        self.total, self.enabled, self.n = max(int(total), 1), enabled, 0
        self.stream = stream or sys.stderr
        self.desc, self.post, self._last, self._t0 = "", "", 0.0, time.monotonic()
        self._tqdm = None
        if enabled:
            try:
                from tqdm import tqdm

                self._tqdm = tqdm(total=self.total, unit="frame", file=self.stream, dynamic_ncols=True)
            except ImportError:
                pass

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_description(self, desc: str) -> None:
        self.desc = desc
        if self._tqdm is not None:
            self._tqdm.set_description(desc)
        else:
            self._draw(force=True)

    def update(self, n: int = 1, postfix: dict | None = None) -> None:
        self.n += n
        if postfix:
            self.post = " ".join(f"{k} {v}" for k, v in postfix.items())
        if self._tqdm is not None:
            self._tqdm.update(n)
            if postfix:
                self._tqdm.set_postfix_str(self.post, refresh=False)
        else:
            self._draw()

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        tty = getattr(self.stream, "isatty", lambda: False)()
        if not force and now - self._last < (0.5 if tty else 10.0) and self.n < self.total:
            return
        self._last = now
        frac = min(self.n / self.total, 1.0)
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        el = now - self._t0
        eta = f"{el / frac - el:5.0f} s left" if frac > 0 else "   ? s left"
        line = f"{self.desc[:28]:28s} [{bar}] {100 * frac:5.1f}% {el:5.0f} s, {eta}  {self.post[:60]}"
        self.stream.write(f"\r{line:160s}" if tty else line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
        elif self.enabled:
            self._draw(force=True)
            if getattr(self.stream, "isatty", lambda: False)():
                self.stream.write("\n")
            self.stream.flush()
