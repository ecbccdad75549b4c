"""``simgap key new --out KEY``: an Ed25519 key pair for signing certificates (simgap[sign]).

    simgap key new --out ~/.simgap/key          # writes key (private, 0600) and key.pub
    SIMGAP_SIGNING_KEY=~/.simgap/key simgap certify data --out cert.json     # signed
    SIMGAP_TRUSTED_KEYS=key.pub simgap synthesize --cert cert.json ...       # verified

What the digests and signatures protect against: docs/deviations.md, "Integrity".
"""

from __future__ import annotations


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("key", help="make a key pair for signing certificates (needs simgap[sign])",
                              description=__doc__)
    sub = p.add_subparsers(dest="key_command", metavar="ACTION")
    n = sub.add_parser("new", help="write a new private key and its .pub public key")
    n.add_argument("--out", required=True, help="private key file to write (the public key goes to OUT.pub)")
    n.set_defaults(func=run_new, outputs=("out",))
    p.set_defaults(func=lambda args: (p.print_help(), 0)[1])


def run_new(args) -> int:
    from ..signing import KEY_ENV, TRUST_ENV, new_key

    priv, pub = new_key(args.out)
    print(f"wrote {priv} (private: keep it to yourself) and {pub} (public: give it to whoever checks your files)")
    print(f"sign: {KEY_ENV}={priv} simgap certify ...   check: {TRUST_ENV}={pub} simgap synthesize --cert ...")
    return 0
