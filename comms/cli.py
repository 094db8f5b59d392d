"""``skycap keys ...``: the fleet's certificate authority and one certificate per drone and ground station.

    skycap keys create --keys ~/skycap-fleet --fleet f1 --drones drone_1,drone_2,drone_3   # CA + gcs + drones
    skycap keys add --keys ~/skycap-fleet drone_4 --role drone                             # one more drone
    skycap keys check --keys /etc/skycap/fleet drone_2        # on a drone: can it join? (exit 1 with the reason)
    skycap keys show --keys ~/skycap-fleet                    # identities, roles, expiry

Then every process of the fleet gets ``transport.security.keys_dir`` (``--zenoh-keys DIR`` on the commands that
join the network) and ``tls/`` endpoints. A drone needs only ``fleet.toml``, ``ca.pem`` and its own
``<id>.pem`` / ``<id>.key``: never copy ``ca.key`` (the CA's private key) to a drone. See :mod:`comms.security`.
"""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("keys", help="create the fleet's CA and certificates (mutual TLS + access control)")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    c = verbs.add_parser("create", help="a new fleet folder: CA, ground station(s), drones")
    c.add_argument("--keys", required=True, help="the fleet folder to create (refused if it holds keys)")
    c.add_argument("--fleet", required=True, help="fleet id (the Zenoh key segment the ACL protects)")
    c.add_argument("--drones", default="", help="comma-separated drone ids, e.g. drone_1,drone_2")
    c.add_argument("--gcs", default="gcs", help="comma-separated ground-station identities (default gcs)")
    c.add_argument("--sim", action="store_true", help="also an identity for the simulator (sim)")
    c.add_argument("--days", type=int, default=365, help="validity of the certificates in days (default 365)")
    c.add_argument("--host", action="append", default=[], help="DNS name or IP written into every certificate "
                   "(for transport.security.verify_name); repeatable")
    c.set_defaults(func=_create)
    a = verbs.add_parser("add", help="issue a certificate for one more identity (needs ca.key)")
    a.add_argument("--keys", required=True)
    a.add_argument("identity", help="the node id it publishes under, e.g. drone_4")
    a.add_argument("--role", required=True, choices=["gcs", "drone", "sim", "router"])
    a.add_argument("--days", type=int, default=365)
    a.add_argument("--host", action="append", default=[])
    a.set_defaults(func=_add)
    k = verbs.add_parser("check", help="check that an identity can join (files, 0600 key, CA, expiry)")
    k.add_argument("--keys", required=True)
    k.add_argument("identity", nargs="?", default=None, help="default: every identity with its files present")
    k.set_defaults(func=_check)
    s = verbs.add_parser("show", help="print the fleet's identities, roles and expiry as JSON")
    s.add_argument("--keys", required=True)
    s.set_defaults(func=_show)


def _ids(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _create(args: argparse.Namespace) -> int:
    from comms.security import FleetKeys

    keys = FleetKeys.create(args.keys, args.fleet, drones=_ids(args.drones), gcs=_ids(args.gcs), sim=args.sim,
                            days=args.days, hosts=args.host)
    print(f"fleet {keys.fleet!r}: CA and {len(keys.identities)} certificate(s) in {keys.folder}")
    for ident, role in sorted(keys.identities.items()):
        print(f"  {role:6s} {ident}: {keys.cert_path(ident).name} + {keys.key_path(ident).name} (0600)")
    print(f"keep {keys.ca_key_path} on this machine only; a drone gets fleet.toml, ca.pem and its own pair")
    return 0


def _add(args: argparse.Namespace) -> int:
    from comms.security import FleetKeys

    keys = FleetKeys.load(args.keys)
    path = keys.add(args.identity, args.role, days=args.days, hosts=args.host)
    print(f"{args.role} {args.identity}: {path} (copy fleet.toml to every node: their ACL lists the identities)")
    return 0


def _check(args: argparse.Namespace) -> int:
    from comms.security import FleetKeys

    keys = FleetKeys.load(args.keys)
    names = [args.identity] if args.identity else [i for i in sorted(keys.identities) if keys.cert_path(i).exists()]
    for ident in names:
        info = keys.check(ident)
        print(f"{ident}: ok ({info['role']}, fleet {info['fleet']}, valid {info['days_left']} more days)")
    return 0


def _show(args: argparse.Namespace) -> int:
    from comms.security import FleetKeys

    keys = FleetKeys.load(args.keys)
    out = {"fleet": keys.fleet, "folder": str(keys.folder), "identities": {}}
    for ident, role in sorted(keys.identities.items()):
        try:
            out["identities"][ident] = keys.check(ident)
        except Exception as e:
            out["identities"][ident] = {"role": role, "problem": str(e)}
    print(json.dumps(out, indent=2))
    return 0
