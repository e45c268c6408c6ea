"""The `vcfusion gen-net` command: a seeded random highway network (vcfusion.traffic.netgen),
built and checked, to reproduce a seed that fails the road frame's property tests."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parsers(sub) -> None:
    p = sub.add_parser("gen-net", help="write a seeded random highway network (plain XML + netconvert) and "
                                       "check the road frame on its routes")
    p.add_argument("--seed", type=int, required=True, help="the network's seed (the property tests name it)")
    p.add_argument("--out", required=True,
                   help="folder for gen.nod/edg/con.xml, gen.net.xml, gen.rou.xml (and gen.flows.rou.xml with --sumo)")
    p.add_argument("--sumo", action="store_true", help="also a short SUMO run: s rate vs speed, d inside the road")
    p.set_defaults(func=cmd_gen_net)


def cmd_gen_net(args: argparse.Namespace) -> int:
    from vcfusion.errors import UsageError
    from vcfusion.traffic import netgen

    if args.seed < 0:
        raise UsageError(f"--seed {args.seed}: expected a non-negative integer")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: is a file; expected a folder (or a path that does not exist yet)")
    try:
        gen = netgen.generate(args.seed, out)
    except RuntimeError as exc:
        raise UsageError(str(exc)) from None
    print(f"seed {args.seed}: {gen.net_file} (changes at the main line's nodes: {', '.join(gen.changes) or 'none'})")
    failed = False
    for name, edges in gen.routes.items():
        p = netgen.frame_properties(gen.net_file, edges)
        bad = netgen.failed_properties(p)
        failed |= bool(bad)
        figures = ", ".join(f"{k} {v:.3f}" for k, v in p.items() if k != "where")
        print(f"  route {name} [{' '.join(edges)}]: {figures}" + (f"  FAILS {'; '.join(bad)}" if bad else ""))
    if args.sumo:
        r = netgen.sumo_properties(gen)
        bad = netgen.failed_sumo_properties(r)
        failed |= bool(bad)
        print(f"  SUMO run: s rate off speed by up to {100 * r['rate_err']:.2f} % over {r['windows']} windows, "
              f"d beyond the road by up to {r['outside_m']:.3f} m in {r['samples']} samples"
              + (f"  FAILS {'; '.join(bad)}" if bad else ""))
    return 1 if failed else 0
