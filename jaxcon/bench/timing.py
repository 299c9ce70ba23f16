"""Timing helpers shared by the benchmarks: the machine's description, CPU steal, compile-and-time."""
from __future__ import annotations

import os
import platform
import time

import jax
import numpy as np


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = jax.devices()[0]
    return {"cpu": cpu, "cores": os.cpu_count(), "platform": dev.platform, "device": dev.device_kind,
            "jax": jax.__version__, "python": platform.python_version()}


def _cpu_jiffies():
    """(steal, total) CPU time of this machine in clock ticks, summed over its CPUs (/proc/stat), or None where
    the file is missing. Steal is time a virtual machine's CPUs were ready to run but the hypervisor ran
    another guest: one sign of a loaded host (contention for shared caches and memory does not show in it)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    ticks = [int(v) for v in fields[1:9]]      # user nice system idle iowait irq softirq steal
    return (ticks[7] if len(ticks) > 7 else 0), sum(ticks)


def steal_fraction(before, after, min_ticks=40):
    """Share of the machine's CPU time stolen by the hypervisor between two `_cpu_jiffies()` readings, or None
    when it cannot be told: no /proc/stat, or fewer than `min_ticks` clock ticks in between (at the usual 100
    ticks per second and CPU, one tick more or less would move a shorter reading by over 2.5 points)."""
    if before is None or after is None or after[1] - before[1] < min_ticks:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


def compile_and_time(fn, *args, repeats=7, stats=None):
    """(compile seconds, median run seconds after compilation, compiled) of jit(fn)(*args).

    stats: an optional dict, filled with the fastest run ("min_s") and the hypervisor's steal share of the
    machine's CPU time during the timed runs ("steal", None where unknown)."""
    jf = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jf.lower(*args).compile()
    t_compile = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    times = []
    before = _cpu_jiffies()
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    if stats is not None:
        stats.update(min_s=float(np.min(times)), steal=steal_fraction(before, _cpu_jiffies()))
    return t_compile, float(np.median(times)), compiled


def _pct(fraction):
    return "   n/a" if fraction is None else f"{100 * fraction:5.1f}%"
