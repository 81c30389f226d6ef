"""Transmission energy over a fading channel and its optimal bit schedule (thesis Eq 3.18-3.19).

Thesis 3.5.3 (after Zhang et al., "Energy-optimal mobile cloud computing under
stochastic wireless channel", its reference [85]): sending ``s`` bits in one
time slot over a channel of gain ``g`` costs

    ``eps_t(s, g) = lambda * s**n / g``                                  (Eq 3.18)

and the robot should spread the ``L`` bits of a task over the ``T`` slots
before its deadline so that the *expected* energy is least:

    ``eps_c* = min over schedules theta = (s_1, ..., s_T), sum s_t = L, of
    E[ sum_t eps_t(s_t, g_t) ]``                                       (Eq 3.19)

The thesis states the problem and does not solve it.  This module solves it.

Assumptions (stated; none is in the thesis beyond Eq 3.18-3.19 themselves)
--------------------------------------------------------------------------
1. Time is cut into ``T`` equal slots; all ``L`` bits must be sent by the end
   of slot ``T`` (a hard deadline), and a slot can carry any number of bits
   (no rate cap: the monomial cost is what limits a slot).
2. The channel gain of each slot is drawn independently from one discrete
   distribution (:class:`Channel`) and is **known at the start of the slot**
   (the robot measures it, e.g. from the received signal strength), never in
   advance.  :meth:`Channel.rayleigh` gives Rayleigh fading (exponentially
   distributed power gain), a common model of a mobile robot's radio link.
3. ``n >= 1`` is the monomial order of the coding scheme (the thesis gives no
   value; Zhang et al. use 2-5).  ``lambda > 0`` (J per bit**n) is not given
   either: it scales every energy alike, so it never changes a schedule.
   With ``n = 1`` and a constant gain Eq 3.18 is Eq 4.4's upload term:
   ``lambda / g = P_u / (8 B_u)`` J per bit (:func:`lambda_from_eq44`), and no
   schedule can save anything.

Solution
--------
* **Known gains** (:func:`schedule_known_gains`, a lower bound: the schedule of
  a robot that knew every future gain): Lagrange multipliers give
  ``s_t = L * w_t / sum w`` with ``w_t = g_t ** (1 / (n - 1))`` and energy
  ``lambda * L**n / (sum w) ** (n - 1)``; for ``n = 1`` every bit goes in the
  best slot.
* **Causal, optimal in expectation** (:class:`OptimalSchedule`, Eq 3.19):
  dynamic programming over the slots left.  With ``k`` slots left, ``b`` bits
  left and the current gain ``g``, the expected cost to go is
  ``lambda * b**n * c_k`` after the current slot is decided, where
  ``c_1 = E[1/g]`` and, for ``n > 1``,
  ``c_k = E[(g ** (1/(n-1)) + c_{k-1} ** (-1/(n-1))) ** -(n-1)]``; the optimal
  share sent now is ``s = b * g**(1/(n-1)) / (g**(1/(n-1)) + c_{k-1}**(-1/(n-1)))``
  (a two-slot Lagrange split between "now" and "the rest", whose equivalent
  gain is ``1 / c_{k-1}``).  For ``n = 1`` the policy sends everything now when
  ``1/g <= c_{k-1}`` and ``c_k = E[min(1/g, c_{k-1})]``.
  The least expected energy of sending ``L`` bits in ``T`` slots is
  ``lambda * L**n * c_T`` (:meth:`OptimalSchedule.expected_energy`).
* The baseline, sending ``L / T`` bits per slot whatever the channel, costs
  ``T * lambda * (L/T)**n * E[1/g]`` (:func:`equal_split_energy`).

Examples
--------
>>> ch = Channel((0.5, 2.0), (0.5, 0.5))
>>> opt = OptimalSchedule(slots=2, channel=ch, order=2)
>>> round(opt.expected_energy(1000, lam=1e-6), 4), round(equal_split_energy(1000, 2, ch, order=2, lam=1e-6), 4)
(0.5632, 0.625)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

__all__ = [
    "Channel",
    "OptimalSchedule",
    "equal_split_energy",
    "lambda_from_eq44",
    "schedule_known_gains",
    "simulate",
    "slot_energy",
]


def _positive(name: str, value: float) -> float:
    from scmr_mesh.errors import InputError

    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _order(n: float) -> float:
    from scmr_mesh.errors import InputError

    v = _positive("order n", n)
    if v < 1:
        raise InputError(f"order n must be >= 1 (energy grows at least linearly with the bits), got {n!r}")
    return v


def slot_energy(bits: float, gain: float, *, lam: float, order: float) -> float:
    """Energy to send ``bits`` in one slot of channel gain ``gain`` (Eq 3.18), J.

    ``lam * bits**order / gain``.

    Examples
    --------
    >>> slot_energy(1000, 2.0, lam=1e-6, order=2)
    0.5
    """
    if bits < 0:
        from scmr_mesh.errors import InputError

        raise InputError(f"bits must be >= 0, got {bits!r}")
    return lam * float(bits) ** order / _positive("gain", gain)


def lambda_from_eq44(p_up_w: float, up_Bps: float, *, gain: float = 1.0) -> float:
    """The energy coefficient that makes Eq 3.18 with ``n = 1`` equal Eq 4.4's upload term, J/bit.

    ``P_u * D / B_u`` joules for ``8 D`` bits at gain ``gain``: ``lambda = gain * P_u / (8 B_u)``.

    Examples
    --------
    >>> lam = lambda_from_eq44(83.54, 3014656)
    >>> round(slot_energy(8 * 1048576, 1.0, lam=lam, order=1), 6)   # robot1, 1 MiB at 23 Mb/s
    29.057391
    """
    return _positive("gain", gain) * _positive("P_u", p_up_w) / (8.0 * _positive("B_u", up_Bps))


@dataclass(frozen=True)
class Channel:
    """An i.i.d. per-slot channel: gain ``gains[i]`` with probability ``probs[i]``.

    Raises
    ------
    InputError
        Empty, non-positive gains, negative probabilities or probabilities not summing to 1.
    """

    gains: tuple[float, ...]
    probs: tuple[float, ...]

    def __post_init__(self) -> None:
        from scmr_mesh.errors import InputError

        g = tuple(_positive("channel gain", x) for x in self.gains)
        p = tuple(float(x) for x in self.probs)
        if not g or len(g) != len(p):
            raise InputError(f"a channel needs one probability per gain, got {len(g)} gains and {len(p)} probabilities")
        if any(not math.isfinite(x) or x < 0 for x in p) or abs(sum(p) - 1.0) > 1e-9:
            raise InputError(f"channel probabilities must be >= 0 and sum to 1, got {p}")
        object.__setattr__(self, "gains", g)
        object.__setattr__(self, "probs", p)

    @classmethod
    def constant(cls, gain: float = 1.0) -> "Channel":
        """A channel that never fades."""
        return cls((gain,), (1.0,))

    @classmethod
    def rayleigh(cls, mean_gain: float = 1.0, *, states: int = 32) -> "Channel":
        """Rayleigh fading: the power gain is exponential with mean ``mean_gain``.

        Discretised into ``states`` equally likely states, each the conditional
        mean of its quantile bin (so the mean gain is exact).  Note that
        ``E[1/g]`` is infinite for the continuous exponential: with a hard
        deadline the last slot may fall in a deep fade, so under continuous
        Rayleigh fading every schedule has unbounded expected energy.  The
        discretised channel bounds the worst gain by the mean of the lowest
        bin, so absolute figures depend on ``states``.
        """
        m = _positive("mean_gain", mean_gain)
        k = int(states)
        if k < 1:
            from scmr_mesh.errors import InputError

            raise InputError(f"states must be >= 1, got {states!r}")
        gains = []
        for i in range(k):
            lo, hi = i / k, (i + 1) / k
            # conditional mean of Exp(1) on the quantile bin [q(lo), q(hi)): k * integral of x e^-x dx
            a = -math.log1p(-lo)
            ea = math.exp(-a)
            if hi >= 1.0:
                part = (a + 1) * ea
            else:
                b = -math.log1p(-hi)
                part = (a + 1) * ea - (b + 1) * math.exp(-b)
            gains.append(m * k * part)
        return cls(tuple(gains), tuple([1.0 / k] * k))

    def mean_inverse(self) -> float:
        """``E[1/g]``."""
        return sum(p / g for g, p in zip(self.gains, self.probs))


def equal_split_energy(bits: float, slots: int, channel: Channel, *, lam: float, order: float) -> float:
    """Expected energy of sending ``bits / slots`` in every slot whatever the gain, J."""
    t = int(slots)
    return t * lam * (float(bits) / t) ** _order(order) * channel.mean_inverse()


def schedule_known_gains(bits: float, gains: Sequence[float], *, lam: float, order: float) -> tuple[list[float], float]:
    """The least-energy schedule when every slot's gain is known in advance (a lower bound).

    Returns
    -------
    (list of float, float)
        Bits per slot and the energy, J.
    """
    n = _order(order)
    g = [_positive("gain", x) for x in gains]
    if not g:
        from scmr_mesh.errors import InputError

        raise InputError("schedule_known_gains needs at least one slot")
    L = float(bits)
    if n == 1.0:
        best = max(range(len(g)), key=lambda i: g[i])
        s = [0.0] * len(g)
        s[best] = L
        return s, lam * L / g[best]
    w = [x ** (1.0 / (n - 1.0)) for x in g]
    total = sum(w)
    return [L * x / total for x in w], lam * L**n / total ** (n - 1.0)


@dataclass
class OptimalSchedule:
    """The causal schedule of least expected energy (Eq 3.19), by dynamic programming.

    Parameters
    ----------
    slots : int
        ``T``, slots before the deadline (>= 1).
    channel : Channel
        The per-slot gain distribution.
    order : float
        ``n`` of Eq 3.18 (>= 1).

    Attributes
    ----------
    coeffs : list of float
        ``coeffs[k - 1] = c_k``: the least expected energy of ``b`` bits over
        ``k`` slots is ``lambda * b**n * c_k``.
    """

    slots: int
    channel: Channel
    order: float = 2.0
    coeffs: list[float] = field(init=False)

    def __post_init__(self) -> None:
        from scmr_mesh.errors import InputError

        if int(self.slots) != self.slots or self.slots < 1:
            raise InputError(f"slots must be an integer >= 1, got {self.slots!r}")
        self.slots = int(self.slots)
        n = self.order = _order(self.order)
        ch = self.channel
        c = [ch.mean_inverse()]
        for _ in range(1, self.slots):
            prev = c[-1]
            if n == 1.0:
                c.append(sum(p * min(1.0 / g, prev) for g, p in zip(ch.gains, ch.probs)))
            else:
                e = 1.0 / (n - 1.0)
                rest = prev ** -e  # the equivalent gain of the remaining slots, to the power 1/(n-1)
                c.append(sum(p * (g**e + rest) ** -(n - 1.0) for g, p in zip(ch.gains, ch.probs)))
        self.coeffs = c

    def expected_energy(self, bits: float, *, lam: float) -> float:
        """``lambda * L**n * c_T``: the least expected energy to send ``bits`` by the deadline, J."""
        return lam * float(bits) ** self.order * self.coeffs[self.slots - 1]

    def send_now(self, bits_left: float, slots_left: int, gain: float) -> float:
        """Bits to send in this slot, given what is left and this slot's gain."""
        b = float(bits_left)
        k = int(slots_left)
        if k <= 1 or b <= 0:
            return max(b, 0.0)
        prev = self.coeffs[k - 2]
        g = _positive("gain", gain)
        if self.order == 1.0:
            return b if 1.0 / g <= prev else 0.0
        e = 1.0 / (self.order - 1.0)
        ge = g**e
        return b * ge / (ge + prev ** -e)


def simulate(schedule: OptimalSchedule, bits: float, gains: Sequence[float], *, lam: float) -> tuple[list[float], float]:
    """Run the causal schedule on one realisation of the slots' gains.

    Returns
    -------
    (list of float, float)
        Bits sent per slot (they sum to ``bits``) and the energy, J.
    """
    if len(gains) != schedule.slots:
        from scmr_mesh.errors import InputError

        raise InputError(f"need one gain per slot ({schedule.slots}), got {len(gains)}")
    left = float(bits)
    sent, energy = [], 0.0
    for i, g in enumerate(gains):
        s = schedule.send_now(left, schedule.slots - i, g)
        sent.append(s)
        energy += slot_energy(s, g, lam=lam, order=schedule.order)
        left -= s
    return sent, energy
