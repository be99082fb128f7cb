"""``snds verify``: a certificate that every controller step decreases V over a box, and its
independent re-check (``--check``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from snds.certify.certificate import (
    VerifyConfig,
    certify,
    read_certificate,
    write_certificate,
)
from snds.certify.recheck import recheck
from snds.errors import ConfigError
from snds.models import load_model

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds verify`` to the subcommands."""
    parser = commands.add_parser(
        "verify",
        help="prove that every Euler step of the controller decreases V over a box "
        "(certificate.json), or re-check a certificate (--check)",
    )
    parser.add_argument("model", type=Path, help="model directory")
    rate = parser.add_mutually_exclusive_group()
    rate.add_argument("--rate", type=float, help="control rate, Hz (default: the data's)")
    rate.add_argument("--dt", type=float, help="control period, s (default: the data's)")
    parser.add_argument("--box", type=float, default=None, help="box half-width, extents (3)")
    parser.add_argument("--dtype", choices=["float64", "float32"], default=None)
    parser.add_argument("--budget", type=int, default=None, help="most cells bounded")
    parser.add_argument("--out", type=Path, default=None, help="default MODEL/certificate.json")
    parser.add_argument(
        "--check", type=Path, default=None, help="re-check this certificate instead"
    )
    parser.set_defaults(run=run)


def _period(args: argparse.Namespace, metrics: dict | None) -> float:
    if args.rate is not None:
        if not args.rate > 0:
            raise ConfigError(f"--rate must be positive, got {args.rate}")
        return 1.0 / args.rate
    if args.dt is not None:
        if not args.dt > 0:
            raise ConfigError(f"--dt must be positive, got {args.dt}")
        return args.dt
    dt = ((metrics or {}).get("stability") or {}).get("dt")
    if dt is None:
        raise ConfigError(
            f"{args.model}: no metrics.json with the data's step; give --rate HZ or --dt S"
        )
    return float(dt)


def run(args: argparse.Namespace) -> int:
    policy, description = load_model(args.model)
    weights = description.get("weights_sha256", "")
    if args.check is not None:
        result = recheck(policy, read_certificate(args.check), weights_sha256=weights)
        if not args.quiet:
            verdict = "confirmed" if result.ok else "REJECTED"
            print(
                f"{args.check}: {verdict}; {result.checked} proven cells re-checked by separate "
                f"code (interval Taylor models, Arb balls), {result.cpu_seconds:.1f} CPU s"
            )
            for line in result.failures[:10]:
                print(f"  {line}")
        return 0 if result.ok else 1
    metrics_file = args.model / "metrics.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else None
    dt = _period(args, metrics)
    options = {
        k: v
        for k, v in {"box_factor": args.box, "dtype": args.dtype, "budget": args.budget}.items()
        if v is not None
    }
    sampled = ((metrics or {}).get("stability") or {}).get("largest_safe_dt")
    certificate = certify(
        policy,
        dt=dt,
        weights_sha256=weights,
        config=VerifyConfig(**options),
        sampled_safe_dt=sampled,
    )
    out = write_certificate(args.out or args.model / "certificate.json", certificate)
    if not args.quiet:
        c = certificate
        best = c["largest_certified_dt"]
        print(
            f"{out}: {c['status']} at {c['rate_hz']:.4g} Hz ({c['dtype']}): "
            f"{100 * c['proven_fraction']:.2f}% of the {c['box_factor']:g}x box proven, "
            f"{len(c['open'])} open ({c['cells_never_bounded']} never bounded within the "
            f"budget) and {len(c['refuted'])} refuted cells, excluded ball "
            f"{c['excluded_radius_user']:.3g} around the target; largest certified step "
            f"{best:.3g} s (sampled largest safe step {sampled if sampled else float('nan'):.3g} "
            f"s); {c['cpu_seconds']:.1f} CPU s"
        )
    return 0
