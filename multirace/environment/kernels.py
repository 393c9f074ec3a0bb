"""The one notice of numba's first compile: the first env built on a machine compiles the package's kernels
(tracks, tyre model, cameras, box raster, renderer: about 10-30 s) and caches them beside the sources; without
a word, that first race looks hung."""
from __future__ import annotations

import sys
from pathlib import Path

NOTICE = ("multirace: compiling the physics and renderer kernels (numba; once per install, about 10-30 s; "
          "later runs load them from the cache)...")
_checked = False


def uncached_kernels() -> list[str]:
    """The numba kernels of the loaded multirace modules that have no cache index yet (they compile on first
    use). Reads numba's dispatcher cache paths, an internal detail: if numba changes them, it finds none."""
    from numba.core.dispatcher import Dispatcher

    missing = []
    for name, module in list(sys.modules.items()):
        if not name.startswith("multirace.") or module is None:
            continue
        for kernel in vars(module).values():
            if not isinstance(kernel, Dispatcher):
                continue
            index = getattr(getattr(getattr(kernel, "_cache", None), "_cache_file", None), "_index_path", None)
            if index is not None and not Path(index).exists():
                missing.append(f"{name}.{kernel.__name__}")
    return missing


def announce_compile(stream=None) -> bool:
    """Print `NOTICE` (to stderr) the first time in a process that kernels are about to compile; returns
    whether it did. Later calls do nothing."""
    global _checked
    if _checked:
        return False
    _checked = True
    if not uncached_kernels():
        return False
    print(NOTICE, file=stream or sys.stderr, flush=True)
    return True
