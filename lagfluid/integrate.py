"""Every forward update a simulator applies, each beside its exact inverse (the training target).

One integrator, outside the models (``docs/architecture.md#conventions``, convention 5; DeepMind GNS
``_decoder_postprocessor``, LagrangeBench ``integrate``): a training target is the inverse of the update
the rollout applies, so a network trained on one-step targets and rolled out by the same update agree by
construction.

The split-step scheme (:mod:`lagfluid.physics.scheme`, paper A.1 and the authors' position updates)::

    advect    v* = v^n + a dt,          x* = x^n + v* dt          advect / advection_target  (drift: a = 0)
    collide   v** (given),              x** = x* + (v** - v*) dt  collide / collision_target
    correct   v^n+1 = v** + a_p dt,     x^n+1 = x** + a_p dt^2    correct / correction_target

End-to-end models (GNS, CConv) use semi-implicit Euler, ``v_{t+1} = v_t + dt a_t``,
``x_{t+1} = x_t + dt v_{t+1}`` (:func:`semi_implicit_euler`; target :func:`acceleration_target` from three
positions as GNS does, or from two velocities). Advection is the same update as semi-implicit Euler.

Every function is pure (new tensors, inputs untouched) and keeps the float operations of the scheme in a
fixed order, so the rollouts are bit-for-bit those of the inline updates it replaced. In floating point an
inverse recovers its input up to rounding: ``((v + a dt) - v) / dt`` differs from ``a`` by about
``eps (|v| + |a| dt) / dt`` (tested in ``tests/test_integrate.py``).
"""

from __future__ import annotations

from torch import Tensor


def semi_implicit_euler(pos: Tensor, vel: Tensor, acc: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """``v' = v + a dt``, ``x' = x + v' dt``.

    Args:
        pos: (N, D) positions (m).
        vel: (N, D) velocities (m/s).
        acc: (N, D) accelerations (m/s^2).
        dt: time step (s).

    Returns:
        ``(pos', vel')``, each (N, D).
    """
    vel_new = vel + acc * dt
    return pos + vel_new * dt, vel_new


def acceleration_target(vel: Tensor, vel_next: Tensor, dt: float) -> Tensor:
    """Inverse of :func:`semi_implicit_euler` (and of :func:`advect`): ``a = (v' - v) / dt``, (N, D)."""
    return (vel_next - vel) / dt


def velocity_from_positions(pos: Tensor, pos_next: Tensor, dt: float) -> Tensor:
    """The velocity semi-implicit Euler stepped with: ``v' = (x' - x) / dt``, (N, D)."""
    return (pos_next - pos) / dt


def acceleration_from_positions(pos_prev: Tensor, pos: Tensor, pos_next: Tensor, dt: float) -> Tensor:
    """GNS's target from three consecutive frames: ``a_t = (x_{t+1} - 2 x_t + x_{t-1}) / dt^2``, (N, D).

    Equal to :func:`acceleration_target` of the two finite-difference velocities, computed that way.
    """
    return acceleration_target(
        velocity_from_positions(pos_prev, pos, dt), velocity_from_positions(pos, pos_next, dt), dt
    )


def advect(pos: Tensor, vel: Tensor, acc: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """The split-step scheme's advection update, ``(x*, v*)``: semi-implicit Euler with ``a`` (N, D)."""
    return semi_implicit_euler(pos, vel, acc, dt)


def drift(pos: Tensor, vel: Tensor, dt: float) -> Tensor:
    """The advection update without an advection stage: ``x* = x^n + v^n dt`` (``v* = v^n``), (N, D)."""
    return pos + vel * dt


def advection_target(vel: Tensor, vel_star: Tensor, dt: float) -> Tensor:
    """Inverse of :func:`advect`: the advection acceleration ``a = (v* - v^n) / dt``, (N, D)."""
    return acceleration_target(vel, vel_star, dt)


def collide(pos_star: Tensor, vel_star: Tensor, vel_collided: Tensor, dt: float) -> Tensor:
    """The collision update of the positions: ``x** = x* + (v** - v*) dt`` (the velocity is ``v**``), (N, D).

    The position takes the velocity change over the whole step, as the authors' code does.
    """
    return pos_star + (vel_collided - vel_star) * dt


def collision_target(vel_star: Tensor, vel_collided: Tensor) -> Tensor:
    """What the collision stage predicts: ``v** - v*``, (N, D)."""
    return vel_collided - vel_star


def correct(pos: Tensor, vel: Tensor, acc_pressure: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """Pressure correction ``v^n+1 = v** + a_p dt``, ``x^n+1 = x** + a_p dt^2``; returns ``(x, v)`` (N, D).

    ``x += a_p dt^2`` is the authors' form; the paper's eq. 28 (``x^{n+1} = x* + v^{n+1} dt``) would move a
    particle twice in one step.
    """
    step = acc_pressure * dt
    return pos + step * dt, vel + step


def correction_target(vel_collided: Tensor, vel_next: Tensor, dt: float) -> Tensor:
    """Inverse of :func:`correct`: the pressure acceleration ``a_p = (v^n+1 - v**) / dt``, (N, D)."""
    return acceleration_target(vel_collided, vel_next, dt)
