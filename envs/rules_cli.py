"""The command-line flags of ``envs.metrics.EvaluationRules``, shared by ``drive.py --evaluate`` and the
benchmarks that evaluate (``bench/compare_drivers.py``), so that every tool names and documents them alike."""

from __future__ import annotations

import argparse

from towndrive.envs.metrics import EvaluationRules


def add_rule_arguments(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """Add the take-over penalty and the Leaderboard 2.0 rule flags; ``prefix`` goes before each help text."""
    parser.add_argument("--takeover-penalty", type=float, default=EvaluationRules.takeover_penalty,
                        help=f"{prefix}score multiplier per safety-driver take-over (envs.metrics)")
    parser.add_argument("--blocked-s", type=float, default=None,
                        help=f"{prefix}Leaderboard 2.0 agent-blocked rule: end a route after this long without moving "
                             "(the Leaderboard: 180)")
    parser.add_argument("--min-speed", action="store_true", help=f"{prefix}Leaderboard 2.0 minimum-speed rule")
    parser.add_argument("--hold-timeout-s", type=float, default=None,
                        help=f"{prefix}penalise standing this long with nothing in the path (the Leaderboard's "
                             "scenario timeout)")


def rules_from_arguments(args: argparse.Namespace) -> EvaluationRules:
    """The rules the flags of ``add_rule_arguments`` chose (one sentence for a value out of range)."""
    return EvaluationRules(args.takeover_penalty, args.blocked_s, args.min_speed, hold_timeout_s=args.hold_timeout_s)
