"""Contacts from the whole array: the public face of contact estimation.

The pieces live in small modules, each holding one thing:

* :mod:`cellbridge.tactile.contact_result` — :class:`Contact`, what is reported;
* :mod:`cellbridge.tactile.clusters` — :func:`cluster_elements`, :func:`force_centroid`;
* :mod:`cellbridge.tactile.disk_model` — the disk's readings with analytic derivatives;
* :mod:`cellbridge.tactile.fit_kernel` — the compiled fit of every contact of a frame;
* :mod:`cellbridge.tactile.fit_problems` — a cluster's data, the kernel's arrays, results;
* :mod:`cellbridge.tactile.two_disks` — two touching contacts in one cluster;
* :mod:`cellbridge.tactile.light_touch` — where a touch without a pressure is;
* :mod:`cellbridge.tactile.spread_model` — the membrane-tension (spread) model with derivatives;
* :mod:`cellbridge.tactile.estimator` — :class:`ContactEstimator`, :func:`estimate_contacts`;
* :mod:`cellbridge.tactile.tracker` — :class:`ContactTracker`, contacts across frames.

This module keeps the names callers have always imported from here.
"""

from cellbridge.tactile.clusters import cluster_elements, force_centroid
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.estimator import ContactEstimator, estimate_contacts

__all__ = [
    "Contact",
    "ContactEstimator",
    "cluster_elements",
    "force_centroid",
    "estimate_contacts",
]
