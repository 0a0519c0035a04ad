"""`omniformation study`: a study file run on Dask (docs/studies.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.cli.args import Parser, int_in


def cluster_address(text: str) -> str:
    """--cluster: a Dask scheduler's tcp://HOST:PORT (or tls://)."""
    import re

    if not re.fullmatch(r"(tcp|tls)://[A-Za-z0-9_.\-\[\]:]+:\d{1,5}", text):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a Dask scheduler's address, tcp://HOST:PORT")
    return text


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    st = sub.add_parser(
        "study", help="run a study (Monte-Carlo, regions of attraction, gain optimisation) on Dask",
        description="Run every point of a study file (docs/studies.md) on a local Dask cluster or a running"
                    " scheduler; results in DIR/results as Parquet, a summary and plots. The same command on the"
                    " same DIR resumes: only runs not yet in results/ are made.")
    st.add_argument("study", type=Path, help="the study file (.toml), e.g. static_config/studies/paper_robustness.toml")
    st.add_argument("--out", type=Path, required=True, metavar="DIR", help="the study's folder (made, or resumed)")
    st.add_argument("--workers", type=int_in(1, 1024), help="local worker processes (default: the CPUs less one, at least 1)")
    st.add_argument("--cluster", type=cluster_address, metavar="tcp://HOST:PORT",
                    help="use a running Dask scheduler (dask scheduler / dask worker) instead of a local cluster")
    st.add_argument("--overwrite", action="store_true", help="start the study in DIR again (its results are removed)")
    st.set_defaults(func=cmd_study)


def cmd_study(args: argparse.Namespace) -> int:
    from app.files import UserError, display_path
    from app.study.session import load_study, run_session

    if args.workers is not None and args.cluster is not None:
        raise UserError("--workers and --cluster: one or the other (a cluster's workers are its own)")
    spec = load_study(args.study)
    result = run_session(spec, args.study, args.out, args.workers, args.cluster, args.overwrite)
    o = result.outcome
    if o.interrupted:
        print(f"study: interrupted: {o.made} runs written this session ({o.skipped + o.made} of {o.total} in"
              f" {display_path(args.out / 'results')}); the same command resumes")
        return 130
    first = f", first result after {o.first_result_s:.1f} s" if o.made else ""
    print(f"study: {o.made} runs made{first}, {o.failed} failed, {o.skipped} already there; {o.seconds:.1f} s")
    if result.best is not None:
        b = result.best
        print("study: best " + ", ".join(f"{k} = {v:.4g}" for k, v in b["values"].items())
              + f" (trial {b['trial']}, objective {b['value']:.4g})")
    for p in [result.summary, *result.plots]:
        print(f"wrote {display_path(p)}")
    return 0
