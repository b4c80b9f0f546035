"""Follow a running keo service: its status, then the next estimates as they are published.

    keo run --config configs/demo.toml          # and the two adapters, or a whole `keo demo`
    python examples/subscribe.py --config configs/demo.toml --count 10

Only the endpoint and the cell's name are taken from the config; `SyncClient("tcp/...",
cell="...")` needs no config at all.
"""

from __future__ import annotations

import argparse

from keo_service import SyncClient


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="the service's keo config (TOML)")
    parser.add_argument("--count", type=int, default=10, help="estimates to print")
    parser.add_argument("--timeout", type=float, default=10.0, help="s to wait for each one")
    args = parser.parse_args(argv)

    with SyncClient.from_config(args.config) as keo:
        status = keo.status(timeout=args.timeout)
        print(f"cell {status.cell}: {status.health}, delay {status.delay_s * 1e3:.1f} ms")
        seen = 0
        for est in keo.estimates(timeout=args.timeout):
            x, y, z = (1e3 * v for v in est.estimate[:3])
            print(
                f"t={est.stamp:.3f} s  error {x:+.3f} {y:+.3f} {z:+.3f} mm  {'|'.join(est.flags)}"
            )
            seen += 1
            if seen == args.count:
                break
    return 0 if seen == args.count else 1


if __name__ == "__main__":
    raise SystemExit(main())
