"""What the estimator reports for one contact: a frozen record, ready for the wire."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Contact"]


@dataclass(frozen=True)
class Contact:
    """One contact on the skin (SI units; positions in the layout's frame).

    ``x, y`` is the best position: the model fit when it succeeded, else the
    centroid. ``force`` and ``diameter`` are the fitted disk's (else the sums of the
    elements and 2√(area/π)); ``area`` is the contact area the elements measured, so
    it leaves out any part of the disk off the skin or in a seam. ``sigma_x/y`` are
    one-sigma position uncertainties under the configured noise, ``sigma_xy`` the
    larger semi-axis of the covariance ``cov``. ``observable`` says per axis whether
    the readings determine that coordinate (False: the value is the middle of the
    consistent range, or σ along it is infinite; an observable axis has a finite σ). ``valid`` is False when no element's inverse gave a pressure
    (too light a touch, or the ambiguous low-pressure region): only the position is
    meaningful then. A hard press that each element alone reads too noisily (on the
    unique high-pressure branch) is fitted and valid.
    """

    x: float
    y: float
    force: float
    area: float
    diameter: float
    centroid_x: float
    centroid_y: float
    model_x: float
    model_y: float
    sigma_x: float
    sigma_y: float
    sigma_xy: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    sigma_force: float
    sigma_diameter: float
    elements: tuple[int, ...]
    valid: bool
    fit_ok: bool
    observable: tuple[bool, bool]
    pressure: float
    force_sum: float
    chi2: float
    dof: int

    def to_dict(self) -> dict[str, object]:
        """Plain dict of Python scalars and lists (msgpack/JSON ready)."""
        # (the instance's own attribute dict copied, its fields in their order: not
        # ``dataclasses.asdict``, whose recursive deep copy was a fifth of a frame's estimate,
        # nor a getattr per field, on the path of every contact to ZeroMQ)
        d = dict(self.__dict__)
        d["cov"] = [list(r) for r in self.cov]
        d["elements"] = list(self.elements)
        d["observable"] = list(self.observable)
        return d

