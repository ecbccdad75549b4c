"""The point of the loop: does the refined model f' give a tighter certified gap and a larger
winning domain than f on the same collected simulator data?

:func:`gap_comparison` certifies the data set twice with the same options, once against the
nominal f (the data set as collected) and once against f' (the same empirical means, f_nom
replaced by f'(x_r, u)), and reports gamma's maximum and mean over the data's (x_r, u) pairs per
state dimension. Given a specification and cell widths it also synthesizes a controller for
x+ in f(x,u) + [-gamma, gamma] and for x+ in f'(x,u) + [-gamma', gamma'] and reports the two
winning-domain sizes (cells).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..systems import System


def gap_comparison(dataset, refined: System, certify_options=None, spec=None, eta=None,
                   hold: int = 1, compose_hold: bool = False) -> dict:
    """Certified gap (gamma max/mean per dimension) and winning-domain size for f and f'.

    Parameters
    ----------
    dataset : simgap.dataset.Dataset
        Collected simulator data (the empirical means are the data of both certificates).
    refined : System
        f' from :func:`simgap.refine.report.refine` on (the transitions of) this data set.
    certify_options : simgap.certify.CertifyOptions, optional
        Used for both certificates (default: the paper's method).
    spec, eta, hold, compose_hold : optional
        Specification, cell widths, hold and hold mode for :func:`simgap.synthesis.controller.synthesize`;
        without ``spec`` and ``eta`` no synthesis is run.
    """
    from ..certify import CertifyOptions, certify

    opts = certify_options or CertifyOptions()
    ds_ref = dataset.with_nominal(refined)
    refined = ds_ref.system
    out = {"certify_options": opts.to_dict()}
    certs = {}
    for tag, ds in (("before", dataset), ("after", ds_ref)):
        cert = certify(ds, opts)
        certs[tag] = cert
        g = np.asarray(cert.gamma(ds.x, ds.u), dtype=float)
        out[f"gamma_max_{tag}"] = g.max(axis=0).tolist()
        out[f"gamma_mean_{tag}"] = g.mean(axis=0).tolist()
        out[f"observed_gap_max_{tag}"] = ds.gap().max(axis=0).tolist()
    if spec is not None and eta is not None:
        from ..synthesis.controller import synthesize
        for tag, sysobj in (("before", dataset.system), ("after", refined)):
            res = synthesize(sysobj, spec, eta, gap=certs[tag], hold=hold, compose_hold=compose_hold)
            st = res.stats
            out[f"winning_{tag}"] = int(st["winning"])
            out["domain_cells"] = int(st["safe_cells"] if st["spec_kind"] == "invariance" else st["cells"])
        out["spec"] = spec.to_dict() if hasattr(spec, "to_dict") else str(spec)
        out["eta"] = np.broadcast_to(np.asarray(eta, dtype=float), (refined.n,)).tolist()
        out["hold"] = int(hold)
        out["compose_hold"] = bool(compose_hold)
    return out
