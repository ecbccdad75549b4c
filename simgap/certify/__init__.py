"""Gap certification: basis, scenario program, bounds, Lipschitz/variance estimates, certificate, audit.

Entry points: :func:`certify` (Dataset -> :class:`Certificate`), :func:`load`, :func:`audit`.
"""

from .bounds import BoundOptions, beta_from_delta, compare_bounds, confidences, delta_from_beta, \
    joint_from_per_dimension
from .certificate import Certificate, load
from .pipeline import CertifyOptions, certify

__all__ = ["certify", "CertifyOptions", "Certificate", "load", "BoundOptions", "beta_from_delta",
           "delta_from_beta", "confidences", "joint_from_per_dimension", "compare_bounds", "audit"]


def audit(*args, **kwargs):
    """See :func:`simgap.certify.audit.audit`."""
    from .audit import audit as _audit
    return _audit(*args, **kwargs)
