"""EMPS: stability of the refinement result under the low-pass cutoff, with and without input filtering.

    python bench/refine_emps_cutoffs.py [--mat PATH]   (default: the record found via $SIMGAP_EMPS_DIR)

Prints, per cutoff, the held-out velocity-update RMS of f and f', their ratio and the effects on
qd in physical units (docs/refine.md, "Results, two cutoffs").
"""

import argparse
from simgap.records import emps_record
from simgap.refine import from_trajectory_file, refine


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mat", help="EMPS estimation record (default: simgap.records.emps_record())")
    args = ap.parse_args()
    args.mat = args.mat or emps_record("estimation")
    for filt in (True, False):
        for fc in (10, 20, 50, 100, 200, 450):
            d = from_trajectory_file(args.mat, preset="emps", cutoff_hz=fc, filter_input=filt)
            r = refine("emps", d).report
            eff = {e["name"]: round(e["physical"]["value"], 2) for e in r["effects"]
                   if e["state"] == 1 and e["physical"]}
            b, a = r["rms_before"][1], r["rms_after"][1]
            print(f"cutoff {fc:4d} Hz input {'filtered  ' if filt else 'unfiltered'}: qd RMS {b:.3g} -> {a:.3g} "
                  f"({b / a:.1f}x)  {eff}  unexplained={r['unexplained']}")


if __name__ == "__main__":
    main()
