"""The model machinery shared by every analytic lobe: parameters, geometry, sums, binding.

A *lobe* (:class:`Lobe`) is one closed-form BRDF term with its own parameter names.  A
*model* (:class:`Model`) is a sum of one or more lobes with public, unambiguous parameter
names; it checks parameters against bounds, applies the below-horizon rule, broadcasts,
and sums values and gradients.  ``gonio.brdf.registry.get_model`` builds models by name.

Parameters not given take their defaults.  Bounds are inclusive and chosen so that each
lobe's directional albedo is <= its weight (``albedo`` or ``ks``) <= 1; a sum of lobes
conserves energy when its linear weights sum to <= 1 (``gonio brdf albedo`` checks).

Conventions (ARCHITECTURE.md): local frame with +z the normal and +x the tangent; ``wi``
towards the light, ``wo`` towards the camera, unit vectors of shape ``(..., 3)``;
``eval`` returns f_r in 1/sr (never times cos).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import ParameterError

Array = NDArray[np.float64]
Params = Mapping[str, ArrayLike]

_CHUNK = 16384  # rows per chunk for large batches: keeps the temporaries in L2 cache

__all__ = ["Array", "BoundModel", "Geometry", "Lobe", "Model", "ParamSpec", "readonly"]


def readonly(a: ArrayLike) -> NDArray[Any]:
    """A read-only view of ``a`` (no copy): how every numba kernel input is passed.

    Why: numba compiles one machine code per argument type, and an array's writeable
    flag is part of its type.  Inputs arrive writeable or not (``np.broadcast_to``, a
    caller's frozen arrays), and each mix was a compilation of its own: 15 of the
    microfacet kernels and 2 of ``rgl_eval`` (~30 s each, cold) in one run of the test
    suite.
    """
    v = np.asarray(a).view()
    v.flags.writeable = False
    return v


@dataclass(frozen=True)
class ParamSpec:
    """One lobe parameter: its bounds (inclusive), default, and whether f is linear in it."""

    name: str
    lower: float
    upper: float
    default: float
    linear: bool = False
    doc: str = ""


class Geometry:
    """Quantities derived from a batch of direction pairs, computed once and shared by the
    lobes of a sum.

    All products use components rather than trigonometric functions, so that the normal
    direction, grazing directions and ``wi == wo`` need no special cases.  ``h`` is the
    *unnormalised* half vector ``wi + wo``.
    """

    def __init__(self, wi: Array, wo: Array) -> None:
        self.wi = wi
        self.wo = wo
        self.ix, self.iy, self.iz = wi[..., 0], wi[..., 1], wi[..., 2]
        self.ox, self.oy, self.oz = wo[..., 0], wo[..., 1], wo[..., 2]

    @cached_property
    def hx(self) -> Array:
        return self.ix + self.ox

    @cached_property
    def hy(self) -> Array:
        return self.iy + self.oy

    @cached_property
    def hz(self) -> Array:
        return self.iz + self.oz

    @cached_property
    def hxy2(self) -> Array:
        """``hx^2 + hy^2`` of the unnormalised half vector."""
        return self.hx * self.hx + self.hy * self.hy

    @cached_property
    def hz2(self) -> Array:
        return self.hz * self.hz

    @cached_property
    def hh(self) -> Array:
        """``|wi + wo|^2``."""
        return self.hxy2 + self.hz2

    @cached_property
    def cos_d(self) -> Array:
        """``dot(wi, h) = dot(wo, h)`` with ``h`` normalised: the cosine Fresnel sees.

        Written as ``|wi + wo| / 2`` (exact for unit vectors), which is symmetric in wi
        and wo and has no cancellation when the two directions are nearly opposite.
        """
        return 0.5 * np.sqrt(self.hh)

    @cached_property
    def si2(self) -> Array:
        """``sin^2(theta_i)`` from the tangential components (exact near the normal)."""
        return self.ix * self.ix + self.iy * self.iy

    @cached_property
    def so2(self) -> Array:
        return self.ox * self.ox + self.oy * self.oy

    @cached_property
    def dot_xy(self) -> Array:
        """``ix ox + iy oy``: the tangential part of ``dot(wi, wo)``."""
        return self.ix * self.ox + self.iy * self.oy


class Lobe:
    """One closed-form BRDF term.  Subclasses set :attr:`kind` and :attr:`specs` and
    implement :meth:`evaluate`.

    Parameters of a lobe are addressed by their *local* names (``"ks"``, ``"alpha"``); a
    :class:`Model` maps public names onto them.
    """

    kind: str = ""
    #: Short human description (shown by ``gonio brdf list``).
    summary: str = ""
    #: Options accepted by the constructor, name -> allowed values (first is the default).
    option_choices: dict[str, tuple[str, ...]] = {}
    isotropic: bool = True

    def __init__(self, **options: str) -> None:
        self.options = {k: v[0] for k, v in self.option_choices.items()}
        self.options.update(options)
        self.specs: tuple[ParamSpec, ...] = self._specs()

    def _specs(self) -> tuple[ParamSpec, ...]:
        raise NotImplementedError

    def evaluate(
        self, g: Geometry, p: dict[str, Array], grad: bool
    ) -> tuple[Array, dict[str, Array] | None]:
        """f_r (1/sr) for directions above the horizon (the caller masks the rest), and,
        when ``grad``, the partial derivatives keyed by local parameter name.

        ``f`` must be a freshly allocated array (the caller zeroes it in place); the
        gradients may be views or broadcastable scalars."""
        raise NotImplementedError

    def lobe_width(self, p: dict[str, Array]) -> Array:
        """Angular width (rad) of the lobe around the half vector ``h = n``: the smallest
        scale the albedo quadrature must resolve."""
        return np.asarray(1.0)

    def aniso_axes(self, p: dict[str, Array]) -> tuple[Array, Array]:
        """Slope widths along +x and +y of an anisotropic lobe (for the albedo quadrature)."""
        return np.asarray(1.0), np.asarray(1.0)


def _as_float_array(name: str, value: ArrayLike) -> Array:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"parameter '{name}' = {value!r} is not a number") from exc
    return arr


@dataclass
class _Slot:
    lobe: Lobe
    index: int  # 1-based position in the sum
    names: dict[str, str] = field(default_factory=dict)  # local -> public


class Model:
    """A BRDF model: a sum of lobes with public parameter names.

    Build models with :func:`gonio.brdf.registry.get_model`; see DEVELOPING.md for the
    contract.  Public attributes: :attr:`name`, :attr:`param_names`, :attr:`bounds`,
    :attr:`defaults`, :attr:`linear_params`, :attr:`options`.
    """

    def __init__(self, lobes: list[Lobe], options: dict[str, str] | None = None) -> None:
        if not lobes:
            raise ValueError("a model needs at least one lobe")
        self.options = dict(options or {})
        self.name = "+".join(lobe.kind for lobe in lobes)
        counts: dict[str, int] = {}
        for lobe in lobes:
            for s in lobe.specs:
                counts[s.name] = counts.get(s.name, 0) + 1
        self._slots: list[_Slot] = []
        specs: dict[str, ParamSpec] = {}
        for i, lobe in enumerate(lobes, start=1):
            slot = _Slot(lobe, i)
            for s in lobe.specs:
                public = s.name if counts[s.name] == 1 else f"{s.name}_{i}"
                slot.names[s.name] = public
                specs[public] = s
            self._slots.append(slot)
        self._specs = specs
        self.param_names: tuple[str, ...] = tuple(specs)
        self.bounds: dict[str, tuple[float, float]] = {
            k: (s.lower, s.upper) for k, s in specs.items()
        }
        self.defaults: dict[str, float] = {k: s.default for k, s in specs.items()}
        self.linear_params: tuple[str, ...] = tuple(k for k, s in specs.items() if s.linear)

    # -- introspection -------------------------------------------------------------------
    @property
    def lobes(self) -> tuple[Lobe, ...]:
        return tuple(s.lobe for s in self._slots)

    @property
    def isotropic(self) -> bool:
        return all(s.lobe.isotropic for s in self._slots)

    def describe_params(self) -> list[tuple[str, float, float, float, bool, str]]:
        """Rows ``(name, lower, upper, default, linear, doc)`` for listings."""
        return [(k, s.lower, s.upper, s.default, s.linear, s.doc) for k, s in self._specs.items()]

    def __repr__(self) -> str:
        opts = "".join(f", {k}={v!r}" for k, v in self.options.items())
        return f"get_model({self.name!r}{opts})"

    # -- parameters ----------------------------------------------------------------------
    def check_params(self, params: Params | None = None) -> dict[str, Array]:
        """Validate parameters and fill in defaults.

        Parameters
        ----------
        params
            Mapping from public parameter name to a float or an array (for example one
            value per colour channel).  Missing parameters take their default.

        Returns
        -------
        dict
            Every parameter of the model as a float64 array.

        Raises
        ------
        ParameterError
            A name is not a parameter of this model, a value is not a number, or a value is
            outside the inclusive bounds (the message names the parameter, the offending
            value and the bounds).
        """
        params = dict(params or {})
        unknown = [k for k in params if k not in self._specs]
        if unknown:
            raise ParameterError(
                f"model '{self.name}' has no parameter {', '.join(map(repr, unknown))}; "
                f"its parameters are: {', '.join(self.param_names)}"
            )
        out: dict[str, Array] = {}
        for k, s in self._specs.items():
            v = _as_float_array(k, params.get(k, s.default))
            ok = (v >= s.lower) & (v <= s.upper)
            if not np.all(ok):
                bad = v[~ok] if v.ndim else v
                bad_v = float(np.ravel(bad)[0])
                raise ParameterError(
                    f"parameter '{k}' of model '{self.name}' = {bad_v:g} is outside its "
                    f"bounds [{s.lower:g}, {s.upper:g}]"
                )
            out[k] = v
        return out

    def _local(self, slot: _Slot, p: dict[str, Array]) -> dict[str, Array]:
        return {local: p[public] for local, public in slot.names.items()}

    # -- evaluation ----------------------------------------------------------------------
    def eval(self, wi: ArrayLike, wo: ArrayLike, params: Params | None = None) -> Array:
        """BRDF value f_r in 1/sr (not multiplied by any cosine).

        Parameters
        ----------
        wi, wo
            Unit directions towards the light and the camera in the local frame, shape
            ``(..., 3)``.
        params
            Parameter values (floats or arrays); missing ones take their defaults.

        Returns
        -------
        ndarray
            Shape ``broadcast(wi.shape[:-1], wo.shape[:-1], *param shapes)``; exactly 0 where
            either direction has ``z <= 0``; NaN where an input direction is NaN.
        """
        return self._eval(wi, wo, params, grad=False)[0]

    def eval_with_grad(
        self, wi: ArrayLike, wo: ArrayLike, params: Params | None = None
    ) -> tuple[Array, dict[str, Array]]:
        """f_r (1/sr) and its analytic partial derivatives with respect to every parameter.

        Returns
        -------
        f, grads
            ``grads[name]`` has the same shape as ``f`` (units 1/sr per unit of ``name``).
        """
        f, g = self._eval(wi, wo, params, grad=True)
        assert g is not None
        return f, g

    def _eval(
        self, wi: ArrayLike, wo: ArrayLike, params: Params | None, grad: bool
    ) -> tuple[Array, dict[str, Array] | None]:
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        if wi.shape[-1:] != (3,) or wo.shape[-1:] != (3,):
            raise ValueError(
                f"directions must have shape (..., 3); got wi {wi.shape}, wo {wo.shape}"
            )
        p = self.check_params(params)
        if not grad and len(self._slots) == 1:
            # A lobe with fused (numba) kernels evaluates the whole batch in one pass,
            # below-horizon rule included; None means "not for these shapes".
            fused = getattr(self._slots[0].lobe, "fused_eval", None)
            f = None if fused is None else fused(wi, wo, self._local(self._slots[0], p))
            if f is not None:
                return f, None
        if (
            not grad
            and wi.ndim == 2
            and wi.shape == wo.shape
            and wi.shape[0] > 2 * _CHUNK
            and all(v.ndim == 0 for v in p.values())
        ):
            # Large batches with scalar parameters: evaluate in cache-sized chunks, which
            # is 2-4x faster than whole-array numpy passes (benchmarks/brdf_eval.py).
            # Components are copied to contiguous rows first: strided (stride 3) operands
            # slow every later numpy pass.
            out = np.empty(wi.shape[0])
            for s in range(0, wi.shape[0], _CHUNK):
                wi_c = np.ascontiguousarray(wi[s : s + _CHUNK].T).T
                wo_c = np.ascontiguousarray(wo[s : s + _CHUNK].T).T
                out[s : s + _CHUNK] = self._eval_checked(wi_c, wo_c, p, False)[0]
            return out, None
        return self._eval_checked(wi, wo, p, grad)

    def _eval_checked(
        self, wi: Array, wo: Array, p: dict[str, Array], grad: bool
    ) -> tuple[Array, dict[str, Array] | None]:
        g = Geometry(wi, wo)
        total: Array | None = None
        grads: dict[str, Array] = {}
        with np.errstate(all="ignore"):
            for slot in self._slots:
                f, lg = slot.lobe.evaluate(g, self._local(slot, p), grad)
                total = f if total is None else total + f
                if grad and lg is not None:
                    for local, public in slot.names.items():
                        grads[public] = lg[local]
            # NaN in z compares False on both tests, so NaN directions stay NaN.
            below = (g.iz <= 0.0) | (g.oz <= 0.0)
            shape = np.broadcast_shapes(below.shape, *(np.shape(v) for v in p.values()))
            assert total is not None
            total = _masked(total, below, shape, inplace=True)
            if grad:
                for k in self.param_names:
                    grads[k] = _masked(grads.get(k, np.zeros(())), below, shape)
        return total, (grads if grad else None)

    def albedo(
        self, theta_i: ArrayLike, params: Params | None = None, phi_i: ArrayLike = 0.0
    ) -> Array:
        """Directional albedo: the integral of f_r cos(theta_o) over the outgoing hemisphere.

        Computed by deterministic quadrature in half-vector space with the lobe width
        resolved (see :mod:`gonio.brdf.albedo`); accurate also for near-mirror lobes.

        Parameters
        ----------
        theta_i
            Incidence angle(s) in radians, in [0, pi/2].
        params
            Parameter values (floats or arrays).
        phi_i
            Incidence azimuth (rad); matters only for anisotropic lobes.

        Returns
        -------
        ndarray
            Dimensionless, shape ``broadcast(theta_i, phi_i, *param shapes)``.
        """
        from gonio.brdf.albedo import lobe_albedo

        p = self.check_params(params)
        total: Array | None = None
        for slot in self._slots:
            a = lobe_albedo(slot.lobe, theta_i, self._local(slot, p), phi_i)
            total = a if total is None else total + a
        assert total is not None
        return total

    def bind(self, params: Params | None = None, channels: int | None = None) -> BoundModel:
        """Fix the parameters: the result evaluates f_r per channel with ``eval(wi, wo)``.

        See :class:`BoundModel`: scalar parameters are broadcast to ``channels`` colour
        channels (by default the length of the array parameters' last axis, or 3).
        """
        return BoundModel(self, params, channels)


def _masked(f: Array, below: Array, shape: tuple[int, ...], inplace: bool = False) -> Array:
    """Zero below the horizon, broadcast to the full output shape, always a fresh array."""
    f = np.asarray(f, dtype=np.float64)
    if inplace and f.shape == shape and below.shape == shape:
        # Saves a full pass on large batches; lobes return a fresh array for f.
        np.copyto(f, 0.0, where=below)
        return f
    return np.where(below, 0.0, np.broadcast_to(f, shape))


class BoundModel:
    """A model with fixed parameters, evaluated per colour channel, for any channel count.

    ``eval(wi, wo)`` returns f_r of shape ``(..., C)`` (1/sr); ``albedo(theta_i)`` returns
    ``(..., C)``.  Same interface as a measured BRDF from ``gonio.brdf.load`` (C = 3) and
    what :meth:`gonio.fitting.FitResult.bind` returns (C = the fit's channels).

    Parameters
    ----------
    model
        The analytic model.
    params
        Name -> float or array; missing names take the model's defaults.  An array's last
        axis is the channel axis, of length C or 1 (broadcast); a scalar is broadcast to C.
    channels
        The channel count C.  By default the length of the array parameters' last axis
        (where it is not 1), or 3 (RGB) when every parameter is a scalar.

    Raises
    ------
    ParameterError
        A parameter is unknown or out of its bounds, or its last axis is neither 1 nor C.
    """

    format = "analytic"

    def __init__(self, model: Model, params: Params | None = None, channels: int | None = None):
        checked = model.check_params(params)
        if channels is None:
            lengths = {v.shape[-1] for v in checked.values() if v.ndim and v.shape[-1] != 1}
            if len(lengths) > 1:
                shapes = ", ".join(f"'{k}' {v.shape}" for k, v in checked.items() if v.ndim)
                raise ParameterError(
                    f"parameters of model '{model.name}' disagree on the number of colour "
                    f"channels (their last axis): {shapes}"
                )
            channels = lengths.pop() if lengths else 3
        if int(channels) != channels or channels < 1:
            raise ParameterError(f"channels must be a positive integer, got {channels!r}")
        self.channels = int(channels)
        self.model = model
        self.params: dict[str, Array] = {}
        for k, v in checked.items():
            if v.ndim and v.shape[-1] not in (1, self.channels):
                raise ParameterError(
                    f"parameter '{k}' must be a scalar or have {self.channels} colour channels "
                    f"(or 1) in its last axis, got shape {v.shape}"
                )
            self.params[k] = np.broadcast_to(v, v.shape[:-1] + (self.channels,))
        values = ", ".join(f"{k}={_fmt(v)}" for k, v in self.params.items())
        self.description = f"{model.name}({values})"
        self.metadata: dict[str, Any] = {
            "model": model.name,
            "options": dict(model.options),
            "params": {k: v.tolist() for k, v in self.params.items()},
        }

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> Array:
        """f_r per channel (1/sr), shape ``broadcast(wi.shape[:-1], wo.shape[:-1]) + (C,)``.

        ``wi`` and ``wo`` are unit vectors, shape (..., 3), in the sample frame.
        """
        wi = np.asarray(wi, dtype=np.float64)[..., None, :]
        wo = np.asarray(wo, dtype=np.float64)[..., None, :]
        return self.model.eval(wi, wo, self.params)

    def albedo(self, theta_i: ArrayLike, phi_i: ArrayLike = 0.0) -> Array:
        """Directional albedo per channel at incidence ``theta_i``, ``phi_i`` (rad).

        Dimensionless, shape ``broadcast(theta_i, phi_i) + (C,)``.
        """
        t = np.asarray(theta_i, dtype=np.float64)[..., None]
        ph = np.asarray(phi_i, dtype=np.float64)[..., None]
        return self.model.albedo(t, self.params, ph)

    def __repr__(self) -> str:
        return f"<BoundModel {self.description}>"


def _fmt(v: Array) -> str:
    flat = np.ravel(v)
    if flat.size and np.all(flat == flat[0]):
        return f"{flat[0]:.6g}"
    return "[" + ", ".join(f"{x:.6g}" for x in flat[:3]) + (", ..." if flat.size > 3 else "") + "]"
