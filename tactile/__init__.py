"""Tactile physics of the two-layer nonlinear element (paper §II.B, §III): pure numpy."""

from typing import TYPE_CHECKING

from cellbridge.tactile.element import (
    EPS0,
    ElementParams,
    capacitance,
    compression,
    forward,
    rest_capacitance,
    sensitivity,
)
from cellbridge.tactile.inversion import (
    DEFAULT_NOISE,
    BranchInfo,
    InverseResult,
    InverseStatus,
    branch_info,
    inverse,
    ratio,
    ratio_slope,
    solve,
)
from cellbridge.tactile.transfer import (
    ChipParams,
    CounterUnwrapper,
    adc_code,
    adc_input,
    adc_mean_band,
    adc_mean_code,
    adc_mean_to_capacitance,
    adc_resolution,
    check_gate,
    code_to_capacitance,
    codes_per_farad,
    counter_delta,
    counter_span,
    counts,
    counts_per_farad,
    counts_to_capacitance,
    expected_counts,
    max_gate_cycles,
    oscillator_period,
    plausible_capacitance,
    sync_min_capacitance,
    unwrap_counts,
)

__all__ = [
    # element (forward model)
    "EPS0",
    "ElementParams",
    "capacitance",
    "compression",
    "forward",
    "rest_capacitance",
    "sensitivity",
    # inverse
    "DEFAULT_NOISE",
    "BranchInfo",
    "InverseResult",
    "InverseStatus",
    "branch_info",
    "inverse",
    "ratio",
    "ratio_slope",
    "solve",
    # transfer functions of the bridge chip
    "ChipParams",
    "CounterUnwrapper",
    "adc_mean_band",
    "check_gate",
    "counter_span",
    "max_gate_cycles",
    "plausible_capacitance",
    "sync_min_capacitance",
    "adc_code",
    "adc_input",
    "adc_mean_code",
    "adc_mean_to_capacitance",
    "adc_resolution",
    "code_to_capacitance",
    "codes_per_farad",
    "counts",
    "counts_per_farad",
    "counter_delta",
    "counts_to_capacitance",
    "expected_counts",
    "oscillator_period",
    "unwrap_counts",
]

# Skin array, calibration and contact estimation (paper §III).
from cellbridge.tactile.calibration import CalibrationConfig, CalibrationStep, Calibrator
from cellbridge.tactile.clusters import cluster_elements, force_centroid
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.contact_surface import ContactSurface
from cellbridge.tactile.layout import (
    SkinLayout,
    grid_layout,
    layout_from_mapping,
    layout_to_toml,
    parse_layout,
)
from cellbridge.tactile.overlap import disk_element_overlap, disk_rect_overlap
from cellbridge.tactile.response import disk_response, pressure_field, skin_response

__all__ += [
    # skin array
    "SkinLayout",
    "disk_element_overlap",
    "disk_rect_overlap",
    "disk_response",
    "grid_layout",
    "layout_from_mapping",
    "layout_to_toml",
    "parse_layout",
    "pressure_field",
    "skin_response",
    # calibration
    "CalibrationConfig",
    "CalibrationStep",
    "Calibrator",
    "ContactSurface",
    # contacts
    "Contact",
    "ContactEstimator",
    "cluster_elements",
    "estimate_contacts",
    "force_centroid",
    # contacts across frames
    "ContactTracker",
    "TrackedContact",
]

# The estimator and the tracker run compiled kernels (numba): imported on first use,
# so what needs only the physics, the layout or the calibration (the emulated mesh,
# the daemon's configuration, the CLI) neither pays for numba nor needs what it
# needs (executable memory, which a unit's MemoryDenyWriteExecute= forbids).
_LAZY = {
    "ContactEstimator": "cellbridge.tactile.estimator",
    "estimate_contacts": "cellbridge.tactile.estimator",
    "ContactTracker": "cellbridge.tactile.tracker",
    "TrackedContact": "cellbridge.tactile.tracker",
}

if TYPE_CHECKING:  # what the lazy names are, for type checkers (no import at run time)
    from cellbridge.tactile.estimator import ContactEstimator, estimate_contacts
    from cellbridge.tactile.tracker import ContactTracker, TrackedContact


def __getattr__(name: str) -> object:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
