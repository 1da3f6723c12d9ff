"""How much memory one input may ask for, checked before it is taken.

A file's header (a sequence's DimSize, a volume's extent and spacing) says how much memory reading
it will need; a hostile or broken header can ask for terabytes. Every reader computes that need
with Python integers (no overflow) and refuses past one limit: ``PROBECAL_MAX_MEMORY_MB``, by
default a quarter of the memory the process may have (physical, ``ulimit -v`` or cgroup).
"""

from __future__ import annotations

import math
import os
import resource
from collections.abc import Iterable
from pathlib import Path

from probecal.core.errors import InputError

ENV = "PROBECAL_MAX_MEMORY_MB"
MB = 1 << 20
PARSED_EXPANSION = 48
"""The most memory a text file parsed into Python objects (JSON, XML, CSV) may take, in times its
size: measured, ``[{"":[]},...]`` takes 32 times its bytes in JSON, ``<a b=''/>`` repeated 38
times in XML (benchmarks/fuzz_inputs.py prints both)."""


def available_memory_bytes() -> int:
    """The memory this process can have (bytes): physical memory, or less under an address-space
    limit (``ulimit -v``) or a cgroup memory limit (a container)."""
    sizes = [os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")]
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        sizes.append(soft)
    try:
        cgroup = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if cgroup.isdigit():
            sizes.append(int(cgroup))
    except OSError:
        pass
    return min(sizes)


def memory_limit_bytes() -> int:
    """The most memory one input may ask for (bytes): ``PROBECAL_MAX_MEMORY_MB`` or a quarter of
    the memory available to this process."""
    value = os.environ.get(ENV)
    if value is None:
        return available_memory_bytes() // 4
    try:
        mb = int(value)
    except ValueError:
        mb = 0
    if mb <= 0:
        raise InputError(None, f"{ENV}={value!r}: not a positive whole number of megabytes")
    return mb * MB


def _size_text(n: int) -> str:
    return f"{n / (1 << 30):.1f} GB" if n >= 1 << 30 else f"{n / MB:.1f} MB"


def checked_bytes(path: str | Path | None, what: str, shape: Iterable[int], itemsize: int = 1) -> int:
    """Bytes that an array of ``shape`` and ``itemsize`` needs; InputError naming ``path`` when a
    size is negative or the total passes the memory limit. Exact for any size (Python integers)."""
    dims = [int(d) for d in shape]
    if any(d < 0 for d in dims):
        raise InputError(path, f"{what} has a negative size {dims}")
    need = math.prod(dims) * int(itemsize)
    limit = memory_limit_bytes()
    if need > limit:
        raise InputError(path, f"{what} would need {_size_text(need)}, more than the limit of "
                               f"{_size_text(limit)} (set {ENV} to change it)")
    return need
