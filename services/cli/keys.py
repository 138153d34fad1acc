"""tessera keys — ZeroMQ CURVE key pairs for the station's hosts (docs/security.md).

Layout of a key directory (keep it on the broker host; only public keys ever leave it)::

    DIR/broker.key, DIR/broker.key_secret    the broker's key pair
    DIR/hosts/<name>.key, <name>.key_secret  one pair per host or program (worker host, bench, web)
    DIR/authorized/<name>.key                public keys the broker admits

``tessera keys init DIR`` makes the broker pair; ``tessera keys add NAME --role ROLE --dir DIR`` a
host pair with its role (what it may register as or submit at the broker), admitted at once;
``role NAME ROLE`` changes an admitted key's role; ``revoke`` removes a host from ``authorized``;
``list`` shows who is admitted, with roles.
Each prints the ``[security]`` lines for the config of the host concerned.
"""

from __future__ import annotations

import sys
from pathlib import Path

from common.bus.security import ROLES


def add_parser(sub) -> None:
    p = sub.add_parser("keys", help="CURVE key pairs: init the broker's, add/revoke/list hosts (docs/security.md)")
    verbs = p.add_subparsers(dest="verb", required=True)
    i = verbs.add_parser("init", help="make the broker's key pair and the authorised-keys directory")
    i.add_argument("dir", help="key directory (on the broker host)")
    a = verbs.add_parser("add", help="make a key pair for a host or program and admit it")
    a.add_argument("name", help="host or program name, e.g. lab-gpu1, bench, web")
    a.add_argument("--dir", required=True, help="key directory made by `tessera keys init`")
    a.add_argument("--role", required=True, choices=ROLES,
                   help="what the key may do: serve that stage (solver, features, matcher, renderer), submit "
                        "captures (scanner), verdicts and re-runs (web), both from one bench PC (bench), only read (subscriber), "
                        "everything (admin)")
    ro = verbs.add_parser("role", help="change the role of an admitted key")
    ro.add_argument("name")
    ro.add_argument("role", choices=ROLES)
    ro.add_argument("--dir", required=True)
    r = verbs.add_parser("revoke", help="stop admitting a host (restart the broker to drop live connections)")
    r.add_argument("name")
    r.add_argument("--dir", required=True)
    ls = verbs.add_parser("list", help="list the admitted public keys")
    ls.add_argument("--dir", required=True)
    p.set_defaults(func=run)


def _broker_snippet(d: Path) -> str:
    return (f"[security]            # broker host\ncurve = true\n"
            f'broker_secret_key = "{d / "broker.key_secret"}"\nauthorized_keys = "{d / "authorized"}"')


def _host_snippet(d: Path, name: str) -> str:
    return (f"[security]            # host {name}: copy broker.key and {name}.key_secret there\ncurve = true\n"
            f'broker_public_key = "{d / "broker.key"}"\nsecret_key = "{d / "hosts" / (name + ".key_secret")}"')


def run(args, out=None) -> int:
    from common.bus.security import check_key_name, generate_keypair, read_role, set_role
    out = out or sys.stdout  # looked up per call: a default bound at import outlives a replaced stdout
    d = Path(args.dir).resolve()
    try:
        if args.verb == "init":
            pub, sec = generate_keypair(d, "broker")
            (d / "authorized").mkdir(exist_ok=True)
            print(f"broker key pair: {pub} (public), {sec} (secret, stays on the broker host)", file=out)
            print(_broker_snippet(d), file=out)
        elif args.verb == "add":
            if not (d / "broker.key").is_file():
                print(f"error: {d} has no broker.key; run `tessera keys init {d}` first", file=sys.stderr)
                return 2
            pub, sec = generate_keypair(d / "hosts", args.name, authorize_in=d / "authorized", role=args.role)
            print(f"key pair of {args.name}: {sec} (secret: copy to that host only); admitted by the broker "
                  f"as {args.role}", file=out)
            print(_host_snippet(d, args.name), file=out)
        elif args.verb == "revoke":
            check_key_name(args.name)   # the names `add` makes: `revoke ../broker` deleted the broker's key
            target = d / "authorized" / f"{args.name}.key"
            if not target.is_file():
                print(f"error: {args.name} is not admitted (no {target})", file=sys.stderr)
                return 2
            target.unlink()
            print(f"{args.name} revoked; restart the broker to drop its live connections", file=out)
        elif args.verb == "role":
            check_key_name(args.name)   # not a path out of authorized/ (as for revoke)
            target = d / "authorized" / f"{args.name}.key"
            if not target.is_file():
                print(f"error: {args.name} is not admitted (no {target})", file=sys.stderr)
                return 2
            set_role(target, args.role)
            print(f"{args.name} is now {args.role} (from its next connection)", file=out)
        elif args.verb == "list":
            for k in sorted((d / "authorized").glob("*.key")):
                print(f"{k.stem:<24} {read_role(k) or '(no role: read only)'}", file=out)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
