"""Gap certification: basis, scenario program, bounds, Lipschitz/variance estimates, certificate, audit.

Entry points: :func:`certify` (Dataset -> :class:`Certificate`), :func:`load`, :func:`audit`.
"""

import importlib

# loaded on first use: the cost estimates of :mod:`simgap.certify.audit` are printed before the
# fitting modules (scipy.stats, the LP solvers: seconds to import) are needed
_LAZY = {"BoundOptions": "bounds", "beta_from_delta": "bounds", "compare_bounds": "bounds",
         "confidences": "bounds", "delta_from_beta": "bounds", "joint_from_per_dimension": "bounds",
         "Certificate": "certificate", "load": "certificate", "CertifyOptions": "pipeline", "certify": "pipeline"}


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["certify", "CertifyOptions", "Certificate", "load", "BoundOptions", "beta_from_delta",
           "delta_from_beta", "confidences", "joint_from_per_dimension", "compare_bounds", "audit"]


def audit(*args, **kwargs):
    """See :func:`simgap.certify.audit.audit`."""
    from .audit import audit as _audit
    return _audit(*args, **kwargs)
