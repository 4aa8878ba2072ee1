"""A virtual mesh whose bridges compute their next samples' counts ahead, as the
real-time bridge shell does (``process_bridge``'s PREFETCH after a wake that sampled)."""

from __future__ import annotations

from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.emulator.realtime.process_bridge import PREFETCH


def prefetch_after_sampling(vm: VirtualMesh) -> None:
    """Make every bridge of ``vm`` compute its next ``PREFETCH`` samples' counts after each
    wake that took a sample, as the real-time shell does."""
    run_one = vm._run

    def prefetching(b: int) -> None:
        fw = vm.nodes[b]
        taken = fw.counters["samples"]
        run_one(b)
        if fw.counters["samples"] > taken:
            fw.sampler.prefetch(PREFETCH)

    vm._run = prefetching  # type: ignore[method-assign]
