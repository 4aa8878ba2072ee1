"""Tactile physics of the two-layer nonlinear element (paper §II.B, §III): pure numpy."""

from cellbridge.tactile.element import (
    EPS0,
    ElementParams,
    capacitance,
    compression,
    forward,
    rest_capacitance,
    sensitivity,
)
from cellbridge.tactile.inverse import (
    DEFAULT_NOISE,
    BranchInfo,
    InverseResult,
    Status,
    branch_info,
    inverse,
    ratio,
    ratio_slope,
    solve,
)
from cellbridge.tactile.transfer import (
    ChipParams,
    adc_code,
    adc_input,
    adc_mean_code,
    adc_mean_to_capacitance,
    adc_resolution,
    code_to_capacitance,
    codes_per_farad,
    counts,
    counts_per_farad,
    counts_to_capacitance,
    expected_counts,
    oscillator_period,
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
    "Status",
    "branch_info",
    "inverse",
    "ratio",
    "ratio_slope",
    "solve",
    # transfer functions of the bridge chip
    "ChipParams",
    "adc_code",
    "adc_input",
    "adc_mean_code",
    "adc_mean_to_capacitance",
    "adc_resolution",
    "code_to_capacitance",
    "codes_per_farad",
    "counts",
    "counts_per_farad",
    "counts_to_capacitance",
    "expected_counts",
    "oscillator_period",
    "unwrap_counts",
]
