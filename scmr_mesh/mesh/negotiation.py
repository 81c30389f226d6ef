"""The request negotiator on a service: ``--queue``, ``--rank`` and the other flags of ``scmr cloud|leader``,
and the setup hook that installs a :class:`~scmr_mesh.qos.negotiator.Negotiator` on a service.

Moved out of :mod:`scmr_mesh.qos.negotiator`, which stays a pure core module (no argparse, no services).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

from scmr_mesh import cliargs as ca
from scmr_mesh.qos.negotiator import Negotiator, UtilityRanking

log = logging.getLogger("scmr_mesh.qos.negotiator")

__all__ = ["add_arguments", "chain", "service_setup"]


def add_arguments(parser) -> None:
    """Add ``--queue``, ``--min-priority``, ``--per-robot`` and the ``--rank`` flags to a service's parser."""
    g = parser.add_argument_group("request negotiator (thesis Table 3.6)")
    g.add_argument(
        "--queue", type=ca.count("waiting requests", lo=0, hi=100000, example="16"), default=None, metavar="N",
        help="rank requests by priority with at most N waiting beyond the workers; the rest get "
             "an immediate 'busy' reply so robots fall back (default: no negotiator, FIFO with "
             "the service's in-flight limit)",
    )
    g.add_argument("--min-priority", type=ca.count("priority", lo=0, hi=1000000, example="0"), default=0, metavar="P",
                   help="with --queue: refuse requests below priority P at once (default 0)")
    g.add_argument("--per-robot", type=ca.count("requests", hi=100000), default=None, metavar="N",
                   help="with --queue: at most N waiting requests per robot (default: no quota)")
    g.add_argument("--rank", choices=("priority", "utility"), default="priority",
                   help="with --queue: serve by willingness to pay (priority, Table 3.6; default) or by the "
                        "Eq 3.14 utility 1/(w_t * t + w_e * expense), t = the request's predicted service time "
                        "(learnt from its size), expense = --price-cpu * t + --price-mb * megabytes")
    num = ca.non_negative("weight", hi=1e9, example="1")
    g.add_argument("--w-time", type=num, default=1.0, metavar="W", help="with --rank utility: omega_t (default 1)")
    g.add_argument("--w-expense", type=num, default=1.0, metavar="W", help="with --rank utility: omega_e (default 1)")
    g.add_argument("--price-cpu", type=num, default=1.0, metavar="P",
                   help="with --rank utility: this server's price per second of service (default 1)")
    g.add_argument("--price-mb", type=num, default=0.0, metavar="P",
                   help="with --rank utility: its price per megabyte received (default 0: shortest job first)")


def service_setup(args) -> Callable[[Any], None] | None:
    """A ``setup(service)`` hook installing a :class:`Negotiator` from parsed flags, or None.

    Raises
    ------
    ValueError
        Through :class:`Negotiator` on bad values (the CLI reports them).
    """
    capacity = getattr(args, "queue", None)
    rank = getattr(args, "rank", "priority")
    if capacity is None:
        if getattr(args, "per_robot", None) is not None or getattr(args, "min_priority", 0) or rank != "priority":
            from scmr_mesh.errors import InputError

            raise InputError("--min-priority, --per-robot and --rank only apply with --queue N; add --queue")
        return None
    from scmr_mesh.errors import InputError

    ranking = None
    if rank == "utility":
        try:
            ranking = UtilityRanking(w_time=args.w_time, w_expense=args.w_expense,
                                     price_per_s=args.price_cpu, price_per_mb=args.price_mb)
        except ValueError as exc:
            raise InputError(f"--rank utility: {exc}; give --w-time or --w-expense > 0") from None

    if capacity < 0:
        raise InputError(f"--queue must be >= 0, got {capacity}")
    if args.per_robot is not None and args.per_robot < 1:
        raise InputError(f"--per-robot must be >= 1, got {args.per_robot}")

    def setup(service) -> None:
        service.use_negotiator(
            Negotiator(capacity=capacity, workers=service.state.workers,
                       min_priority=args.min_priority, per_robot=args.per_robot, ranking=ranking)
        )
        log.info("negotiator: queue %d, %d workers, min priority %d, per-robot %s, rank by %s",
                 capacity, service.state.workers, args.min_priority, args.per_robot,
                 "priority" if ranking is None else f"utility ({ranking})")

    return setup


def chain(*hooks: Callable[[Any], None] | None) -> Callable[[Any], None] | None:
    """One setup hook calling each non-None hook in order (None if there are none)."""
    live = [h for h in hooks if h is not None]
    if not live:
        return None

    def setup(service) -> None:
        for h in live:
            h(service)

    forks = [h.prefork for h in live if callable(getattr(h, "prefork", None))]
    if forks:  # hooks that fork a process before the service's workers and zenoh start
        def prefork(node: str) -> None:
            for f in forks:
                f(node)

        setup.prefork = prefork
    return setup
