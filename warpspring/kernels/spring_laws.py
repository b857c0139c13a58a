"""Spring force laws, the maths of one spring in typed ``@wp.func`` helpers: ``SpringLaw`` (which parts beyond
Hooke's spring with an axial damper a kernel compiles), the law's values read from the input table
(``spring_law_type``), and per precision and law one spring's force, energy and stiffness matrix
(``spring_funcs``) and the branch helpers the plastic pass shares (``spring_branch_funcs``).

Per spring (i, j), d = xj - xi: the force on i is (T(|d|) + kd (vj - vi)·d̂) d̂ with T = ke (|d| - L).
Springs may follow other laws per spring: square, T = ke Δ|Δ| with Δ = |d| - L, and a compression branch of
its own stiffness, ratio × ke for Δ < 0; plastic springs keep their rest lengths per world (a negative rest
length marks a broken spring, which carries no force). The spring family that sums these per particle, and
the spring passes, are in ``springs.py``.
"""

import functools
from typing import NamedTuple

import warp as wp

from .inputs import INPUT_BIPHASIC_RATIO, INPUT_BIPHASIC_STRAIN, INPUT_MAX_SPRING_FORCE
from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})

#: Particles closer than this [m] are coincident: their spring has no direction and exerts no force.
COINCIDENT_DISTANCE = 1.0e-12

#: Per-spring law codes (``SpringArrays.law``): T = ke Δ (linear) or T = ke Δ|Δ| (square), Δ = |d| - L.
SPRING_LINEAR = 0
SPRING_SQUARE = 1
#: The rest length [m] of a broken (plastic) spring: it carries no force, stiffness, strain or energy.
BROKEN_REST_LENGTH = -1.0


class SpringLaw(NamedTuple):
    """Which parts of the spring force law beyond Hooke's spring with an axial damper a kernel compiles.

    Only the switches live here; the values (knee strain, stiffness ratio, force limit) are live inputs
    read from the input table (``inputs.py``), so changing them compiles nothing.

    The material switches (``square``, ``asymmetric``, ``plastic``) say that *some* springs use a part: which
    ones, and with what values, the per-spring arrays of ``SpringArrays`` say (``law``, ``compression_ratio``,
    a per-world ``rest_length``), so a scene compiles only the laws its spring groups use.

    Attributes:
        biphasic: springs stiffen by ``INPUT_BIPHASIC_RATIO`` beyond the strain ``INPUT_BIPHASIC_STRAIN``.
        clamp_force: a spring's force magnitude, elastic plus damping, is clamped to ``INPUT_MAX_SPRING_FORCE``.
        square: springs whose ``law`` is ``SPRING_SQUARE`` pull with T = ke Δ|Δ| (ke in N/m²).
        asymmetric: in compression (Δ < 0) a spring's stiffness is ``compression_ratio`` × ke.
        plastic: rest lengths are state, one per world and spring (``rest_length`` world-major, moved by
            ``spring_plastic_kernel`` after each step); a negative one marks a broken spring.
    """

    biphasic: bool = False
    clamp_force: bool = False
    square: bool = False
    asymmetric: bool = False
    plastic: bool = False

    @property
    def per_spring(self) -> bool:
        """Whether the law reads per-spring law arrays (``SpringArrays.law``, ``compression_ratio``)."""
        return self.square or self.asymmetric


#: The plain law: f = (ke (|d| - L) + kd (vj - vi)·d̂) d̂.
HOOKE = SpringLaw()


@functools.cache
def spring_law_type(scalar: type):
    """The struct of a spring law's values, read once per thread from the input table."""

    @wp.struct
    class SpringLawValues:
        knee_strain: scalar  # strain beyond which a biphasic spring stiffens [-]
        extra_stiffness: scalar  # stiffness ratio beyond the knee, minus one [-]
        max_force: scalar  # largest magnitude of a spring's force [N]
        square: wp.int32  # this spring's law is square (SPRING_SQUARE); set per spring by ``law_at``
        compression_ratio: scalar  # this spring's compression stiffness / ke [-]; set per spring by ``law_at``

    return SpringLawValues


@functools.cache
def spring_branch_funcs(scalar: type, law: SpringLaw = HOOKE):
    """(branch_stiffness, base_stretch_at) of one precision and law: the stiffness of the branch a stretch is
    on, and the inverse of the base law (before the biphasic excess) on a branch."""
    SpringLawValues = spring_law_type(scalar)

    @wp.func
    def branch_stiffness(stretch: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """The stiffness of the branch ``stretch`` Δ [m] is on: ke, or in compression ratio × ke (asymmetric)."""
        if wp.static(law.asymmetric):
            return wp.where(stretch < scalar(0.0), values.compression_ratio * ke, ke)
        return ke

    @wp.func
    def base_stretch_at(magnitude: scalar, k: scalar, values: SpringLawValues) -> scalar:
        """|Δ| [m] at which the base law of stiffness k reaches the tension magnitude ``magnitude`` ≥ 0 [N]:
        magnitude / k, or √(magnitude / k) for a square spring."""
        s = magnitude / wp.max(k, scalar(1.0e-30))
        if wp.static(law.square):
            s = wp.where(values.square != 0, wp.sqrt(s), s)
        return s

    return branch_stiffness, base_stretch_at


@functools.cache
def spring_funcs(scalar: type, law: SpringLaw = HOOKE):
    """(spring_law_values, spring_force, spring_energy, spring_stiffness_matrix) of one precision and law.

    ``spring_law_values(inputs, world)`` loads the law's values from the input table (only those the law uses);
    the other three take them as their last argument.
    """
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    SpringLawValues = spring_law_type(scalar)
    branch_stiffness, base_stretch_at = spring_branch_funcs(scalar, law)

    @wp.func
    def spring_law_values(inputs: wp.array2d[scalar], world: int) -> SpringLawValues:
        """The law's values from a world's row of the input table."""
        values = SpringLawValues()
        if wp.static(law.biphasic):
            values.knee_strain = inputs[world, INPUT_BIPHASIC_STRAIN]
            values.extra_stiffness = inputs[world, INPUT_BIPHASIC_RATIO] - scalar(1.0)
        if wp.static(law.clamp_force):
            values.max_force = inputs[world, INPUT_MAX_SPRING_FORCE]
        return values

    @wp.func
    def excess(length: scalar, rest: scalar, values: SpringLawValues) -> scalar:
        """Stretch beyond the biphasic knee [m] (0 below it)."""
        return wp.max(length - rest * (scalar(1.0) + values.knee_strain), scalar(0.0))

    @wp.func
    def base_tension(stretch: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """The law's tension [N] at the stretch Δ [m] before the biphasic excess: k Δ, or k Δ|Δ| (square)."""
        t = branch_stiffness(stretch, ke, values) * stretch
        if wp.static(law.square):
            t = wp.where(values.square != 0, t * wp.abs(stretch), t)
        return t

    @wp.func
    def intact(rest: scalar) -> scalar:
        """1 for a spring that carries force, 0 for a broken one (plastic law: negative rest length)."""
        if wp.static(law.plastic):
            return wp.where(rest < scalar(0.0), scalar(0.0), scalar(1.0))
        return scalar(1.0)

    @wp.func
    def tension(length: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """Elastic tension T(|d|) [N], positive when stretched."""
        t = base_tension(length - rest, ke, values)
        if wp.static(law.biphasic):
            t += values.extra_stiffness * ke * excess(length, rest, values)
        return t

    @wp.func
    def tension_slope(length: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """dT/d|d| [N/m]: k, or 2k|Δ| (square), on the stretch's branch; plus the biphasic excess beyond the knee."""
        stretch = length - rest
        slope = branch_stiffness(stretch, ke, values)
        if wp.static(law.square):
            slope = wp.where(values.square != 0, scalar(2.0) * slope * wp.abs(stretch), slope)
        if wp.static(law.biphasic):
            slope += wp.where(excess(length, rest, values) > scalar(0.0), values.extra_stiffness * ke, scalar(0.0))
        return slope

    @wp.func
    def spring_force(
        xi: vec3, xj: vec3, vi: vec3, vj: vec3, rest: scalar, ke: scalar, kd: scalar, values: SpringLawValues
    ) -> vec3:
        """Force [N] on particle i of the spring (i, j): (T(|d|) + kd (vj - vi)·d̂) d̂, d = xj - xi, with
        T = ke (|d| - L) for Hooke's law (see ``SpringLaw``); its magnitude clamped if the law says so.

        Coincident particles (|d| below ``COINCIDENT_DISTANCE``) give a zero force, never NaN.
        """
        d = xj - xi
        length = wp.length(d)
        # Branch-free guard (the gather's unrolled slots stay free of branches): n = 0 when coincident.
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        magnitude = tension(length, rest, ke, values) + kd * wp.dot(vj - vi, n)
        if wp.static(law.clamp_force):
            magnitude = wp.clamp(magnitude, -values.max_force, values.max_force)
        if wp.static(law.plastic):
            magnitude *= intact(rest)
        return n * magnitude

    @wp.func
    def spring_stiffness_matrix(
        xi: vec3, xj: vec3, rest: scalar, ke: scalar, clamp: bool, values: SpringLawValues
    ) -> mat33:
        """∂f_i/∂x_j [N/m] of the spring (i, j): T'(|d|) d̂d̂ᵀ + (T/|d|)(I - d̂d̂ᵀ), for Hooke's law
        ke (d̂d̂ᵀ + (1 - L/|d|)(I - d̂d̂ᵀ)); ∂f_i/∂x_i is its negative. (The force clamp is not
        differentiated: implicit integration linearises the unclamped law.)

        With ``clamp`` the transverse term of a compressed spring (|d| < L, negative) is dropped, so the
        matrix stays positive semi-definite, as implicit integration needs. Coincident particles give 0.
        """
        d = xj - xi
        length = wp.length(d)
        inv_length = wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        n = d * inv_length
        nn = wp.outer(n, n)
        transverse = tension(length, rest, ke, values) * inv_length
        if clamp:
            transverse = wp.max(transverse, scalar(0.0))
        axial = wp.where(
            length > scalar(COINCIDENT_DISTANCE), tension_slope(length, rest, ke, values), scalar(0.0)
        )
        return intact(rest) * (axial * nn + transverse * (wp.identity(n=3, dtype=scalar) - nn))

    @wp.func
    def stretch_at(magnitude: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """The stretch |d| - L [m] ≥ 0 at which the tension reaches ``magnitude`` ≥ 0 [N] (T is increasing)."""
        s = base_stretch_at(magnitude, ke, values)
        if wp.static(law.biphasic):
            knee = rest * values.knee_strain
            if s > knee:
                extra = values.extra_stiffness * ke
                rest_of_force = magnitude - base_tension(knee, ke, values)
                s = knee + rest_of_force / wp.max(ke + extra, scalar(1.0e-30))
                if wp.static(law.square):
                    if values.square != 0:
                        # ke s² + extra (s - knee) = magnitude: the positive root.
                        b = extra / wp.max(ke, scalar(1.0e-30))
                        c = (magnitude + extra * knee) / wp.max(ke, scalar(1.0e-30))
                        s = scalar(0.5) * (wp.sqrt(b * b + scalar(4.0) * c) - b)
        return s

    @wp.func
    def law_energy(stretch: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """∫₀^stretch T [J] of the unclamped law: ½ k Δ², or k |Δ|³/3 (square), on the stretch's branch."""
        k = branch_stiffness(stretch, ke, values)
        energy = scalar(0.5) * k * stretch * stretch
        if wp.static(law.square):
            energy = wp.where(values.square != 0, k * wp.abs(stretch) * stretch * stretch / scalar(3.0), energy)
        if wp.static(law.biphasic):
            e = wp.max(stretch - rest * values.knee_strain, scalar(0.0))
            energy += scalar(0.5) * values.extra_stiffness * ke * e * e
        return energy

    @wp.func
    def spring_energy(xi: vec3, xj: vec3, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """Elastic energy [J] of the spring (i, j), the potential of its elastic force: ∫ T = ½ ke (|d| - L)²
        (+ the biphasic excess term); with the force clamp, T held at ±max_force beyond the stretch where it
        reaches it (the damper's share of the clamp is not a potential and is left out)."""
        if wp.static(law.plastic):
            if rest < scalar(0.0):
                return scalar(0.0)  # broken
        stretch = wp.length(xj - xi) - rest
        if wp.static(law.clamp_force):
            limit = wp.max(values.max_force, scalar(0.0))
            tension_value = tension(stretch + rest, rest, ke, values)
            if wp.abs(tension_value) > limit:
                knee = stretch_at(limit, rest, ke, values)
                if tension_value < scalar(0.0):
                    # compression: the base law's compression branch only
                    knee = -base_stretch_at(limit, branch_stiffness(-scalar(1.0), ke, values), values)
                return law_energy(knee, rest, ke, values) + limit * wp.abs(stretch - knee)
        return law_energy(stretch, rest, ke, values)

    return spring_law_values, spring_force, spring_energy, spring_stiffness_matrix
