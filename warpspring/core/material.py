"""Cloth materials in physical units, mapped to spring and hinge parameters that do not depend on resolution.

A :class:`ClothMaterial` states what a fabric is (membrane stiffness E·t and G·t [N/m], bending stiffness
D [N·m], areal density [kg/m²]); the functions here turn it into per-spring stiffness ke [N/m] and damping
kd [N·s/m], per-hinge stiffness k_θ [N·m/rad] and damping [N·m·s/rad], and lumped particle masses [kg],
so that a cloth of 16² and of 128² particles stores the same energy for the same deformation. All are
vectorised NumPy functions of the rest geometry (float64 in, float64 out).

Conventions: small-strain energy density W = ½ vᵀ C v [J/m²] with v = (ε_xx, ε_yy, γ_xy = 2ε_xy) and C in
N/m; an affine strain ε stretches a spring of rest length L along the unit vector n by L·(n·ε·n) to first
order, storing ½ k L² (n·ε·n)². A hinge stores ½ k_θ (θ - θ₀)², θ its dihedral angle (0 when flat).

Damping is a Kelvin-Voigt viscosity proportional to the stiffness: the membrane's viscous stress is
τ C ε̇ with the retardation time τ = stretch_damping / stretch, so a spring gets kd = τ·ke (the viscous
modulus along the warp is then exactly ``stretch_damping``), and a hinge gets kd_θ = (bending_damping /
bending)·k_θ. A mode of angular frequency ω is then damped by ζ = τω/2 at any resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from .. import checks
from ..errors import ConfigError

#: Poisson's ratio of a network of edge springs built by :func:`edge_springs` (Van Gelder's rule).
MESH_POISSON_RATIO = 1.0 / 3.0

_UNITS = {
    "stretch": "N/m",
    "shear": "N/m",
    "bending": "N·m",
    "density": "kg/m²",
    "stretch_damping": "N·s/m",
    "bending_damping": "N·m·s",
}


@dataclass(frozen=True, kw_only=True)
class ClothMaterial:
    """A thin sheet's elastic, viscous and inertial properties per unit area, along its warp/weft axes.

    Attributes:
        stretch: membrane Young's modulus times thickness E·t [N/m], > 0: the force per unit width per unit
            strain of a strip pulled along the warp (or weft) and free to contract sideways.
        shear: in-plane shear modulus times thickness G·t [N/m], > 0 (warp-weft shear, "trellising").
        bending: bending stiffness per unit width D [N·m], > 0 (E t³ / 12(1-ν²) for an elastic plate): a
            cylinder of curvature κ stores ½ D κ² per unit area.
        density: areal density [kg/m²], > 0.
        stretch_damping: membrane viscosity [N·s/m], ≥ 0: the viscous counterpart of ``stretch``.
        bending_damping: bending viscosity [N·m·s], ≥ 0: the viscous counterpart of ``bending``.
    """

    stretch: float
    shear: float
    bending: float
    density: float
    stretch_damping: float = 0.0
    bending_damping: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            check = checks.non_negative if f.name.endswith("_damping") else checks.positive
            value = check(f"ClothMaterial.{f.name} [{_UNITS[f.name]}]", getattr(self, f.name))
            object.__setattr__(self, f.name, value)


#: KES (Kawabata) units in SI: bending B [gf·cm²/cm → N·m], shear G [gf/(cm·deg) → N/m per rad], and the
#: load 500 gf/cm [N/m] at which the strain EMT is measured.
KES_BENDING = 9.80665e-3 * 1.0e-4 / 1.0e-2
KES_SHEAR = 9.80665e-3 / 1.0e-2 * 180.0 / math.pi
KES_EMT_LOAD = 500.0 * 9.80665e-3 / 1.0e-2


def kes_material(*, bending: float, shear: float, emt: float, density: float) -> ClothMaterial:
    """A :class:`ClothMaterial` from Kawabata (KES-F) values: B [gf·cm²/cm], G [gf/(cm·deg)], EMT [%] (strain at
    500 gf/cm) and areal density [kg/m²]. Woven fabrics are non-linear (soft at first, stiffening as the crimp
    straightens): ``stretch`` is the secant 500 gf/cm / EMT, not the initial slope."""
    return ClothMaterial(stretch=KES_EMT_LOAD / (checks.positive("emt [%]", emt) / 100.0),
                         shear=KES_SHEAR * shear, bending=KES_BENDING * bending, density=density)


#: Cotton shirting, ~130 g/m²: representative values, NOT from a measurement of one fabric (B ≈ 0.05
#: gf·cm²/cm, G ≈ 0.9 gf/(cm·deg), EMT ≈ 10 %); no retrievable source found (``PRESET_SOURCES``).
COTTON = ClothMaterial(stretch=5.0e3, shear=50.0, bending=5.0e-6, density=0.13)
#: A light silk-like woven (charmeuse, ~16 momme ≈ 70 g/m²): representative, NOT measured (B ≈ 0.01
#: gf·cm²/cm, G ≈ 0.35 gf/(cm·deg)); no retrievable source found.
SILK = ClothMaterial(stretch=2.0e3, shear=20.0, bending=1.0e-6, density=0.07)
#: Denim: fabric A of Kumari & Khurana, "Regenerated cellulose-based denim fabric for tropical regions",
#: J. Textiles 2016, art. 4614168, table 5 (KES-F: B = 0.172 gf·cm²/cm, G = 2.180 gf/(cm·deg),
#: EMT = 5.515 %); density 0.41 kg/m² (12 oz/yd²) NOT from that table (see ``PRESET_SOURCES``).
DENIM = kes_material(bending=0.172, shear=2.180, emt=5.515, density=0.41)
#: Natural-rubber sheet 1 mm thick: E = 1.5 MPa, ν = 0.5, 930 kg/m³ (handbook values): E·t = 1.5e3 N/m,
#: G·t = E·t / 2(1+ν), D = E t³ / 12(1-ν²). Isotropic: on a grid it keeps E and G but gets ν ≈ 0.30.
RUBBER_SHEET = ClothMaterial(stretch=1.5e3, shear=5.0e2, bending=1.5e-3 / 9.0, density=0.93)


def wang2011_material(*, density: float, stretching, bending) -> ClothMaterial:
    """A :class:`ClothMaterial` from a fabric measured by Wang, O'Brien & Ramamoorthi 2011 ("Data-driven elastic
    models for cloth: modeling and measurement", ACM TOG 30(4):71, doi:10.1145/2010324.1964966), as their data is
    distributed with the ARCSim simulator (``materials/<fabric>.json``).

    Args:
        density: the file's ``density`` [kg/m²].
        stretching: the first row of the file's ``stretching`` table, (k0, k1, k2, k3) [N/m]: its stiffness at
            zero strain (the row ARCSim uses for every direction at small strain).
        bending: the first column of the file's ``bending`` table, its stiffness at zero curvature along the warp,
            the bias and the weft (ARCSim's three directions, 0°, 45°, 90°) [N·m, ARCSim's hinge form].

    How ARCSim uses them (``dde.cpp``, ``physics.cpp``), and what they are in this module's terms:

    - Membrane: ARCSim doubles each entry and stores ½ k0' ε_uu² + k1' ε_uu ε_vv + ½ k2' ε_vv² + k3' ε_uv² per unit
      area (k' = 2k, ε Green's strain), so C11 = 2 k0, C12 = 2 k1, C22 = 2 k2 and, with γ = 2 ε_uv, G·t = k3.
      ``stretch`` is the mean of the uniaxial-stress moduli along warp and weft, C11 - C12²/C22 and
      C22 - C12²/C11: a :class:`ClothMaterial` has one (woven fabrics differ by up to 5× between the two).
    - Bending: ARCSim's hinge force is ke · |e|² / (2 (A1 + A2)) · θ ∇θ / 2, the energy ke |e|² θ² / (8 (A1 + A2));
      :func:`hinge_parameters`' discrete-shells hinge stores D |e|² θ² / (2 (A1 + A2)), so D = ke / 4.
      ``bending`` is the mean of the three directions' D (the measured anisotropy, up to 1.5×, is not kept),
      at zero curvature (the measured stiffness falls by up to 3× towards ARCSim's largest sample, 40 /m).
    """
    values = list(stretching)
    if len(values) != 4:
        raise ConfigError(f"stretching must be the 4 entries (k0, k1, k2, k3) of the file's first row, got {len(values)}")
    k0, k2, k3 = (checks.positive(f"stretching entry k{i} [N/m]", values[i]) for i in (0, 2, 3))
    k1 = checks.non_negative("stretching entry k1 [N/m]", values[1])
    c11, c12, c22 = 2.0 * k0, 2.0 * k1, 2.0 * k2
    stretch = 0.5 * ((c11 - c12**2 / c22) + (c22 - c12**2 / c11))
    bends = [checks.positive("bending entry [N·m]", v) for v in bending]
    if len(bends) != 3:
        raise ConfigError(f"bending must give the 3 directions (warp, bias, weft), got {len(bends)} values")
    return ClothMaterial(stretch=stretch, shear=k3, bending=sum(bends) / 12.0, density=density)


#: Wang et al. 2011's "11oz-black-denim" (jeans, 99 % cotton 1 % spandex): ARCSim ``materials/11oz-black-denim.json``.
DENIM_11OZ = wang2011_material(density=0.324, stretching=(205.352005, 10.234077, 1013.88629, 53.387184),
                               bending=(64.196457e-6, 73.384567e-6, 96.951576e-6))
#: Wang et al. 2011's "royal-target" (pants, 65 % cotton 35 % polyester): ARCSim ``materials/royal-target.json``.
COTTON_POLYESTER = wang2011_material(density=0.220, stretching=(2016.55456, 9.170511, 2034.97644, 104.759674),
                                     bending=(125.409805e-6, 107.997696e-6, 125.409805e-6))
#: Wang et al. 2011's "white-dots-on-blk" (tablecloth, 100 % polyester): ARCSim ``materials/white-dots-on-blk.json``.
POLYESTER = wang2011_material(density=0.128, stretching=(2002.08618, 0.345588, 2027.48559, 19.189022),
                              bending=(51.713814e-6, 40.659470e-6, 31.282822e-6))
#: CLO3D's fabric units in SI: weight g/m² → kg/m², stretch and shear g/s² → N/m, bending g·mm²/s² → N·m.
CLO_WEIGHT = 1.0e-3
CLO_STIFFNESS = 1.0e-3
CLO_BENDING = 1.0e-3 * 1.0e-6


def clo_material(*, weight: float, stretch, shear: float, bending) -> ClothMaterial:
    """A :class:`ClothMaterial` from fabric parameters in CLO3D's input units, as published for measured fabrics.

    Args:
        weight: areal mass [g/m²].
        stretch: (warp, weft) stretch stiffness [g/s²], read as E·t (1 g/s² = 1e-3 N/m).
        shear: shear stiffness [g/s²], read as G·t.
        bending: (warp, weft) bending stiffness [g·mm²/s²], read as D (1 g·mm²/s² = 1e-9 N·m).

    A :class:`ClothMaterial` is isotropic: ``stretch`` is the mean of warp and weft, ``bending`` the mean of warp
    and weft (the fabrics below differ by up to 3.2× between them).
    """
    warp, weft = (checks.positive("stretch [g/s²]", v) for v in _pair("stretch", stretch))
    b_warp, b_weft = (checks.positive("bending [g·mm²/s²]", v) for v in _pair("bending", bending))
    return ClothMaterial(stretch=CLO_STIFFNESS * 0.5 * (warp + weft), shear=CLO_STIFFNESS * checks.positive("shear [g/s²]", shear),
                         bending=CLO_BENDING * 0.5 * (b_warp + b_weft),
                         density=CLO_WEIGHT * checks.positive("weight [g/m²]", weight))


def _pair(name: str, value) -> tuple[float, float]:
    values = list(value)
    if len(values) != 2:
        raise ConfigError(f"{name} must be the (warp, weft) pair, got {len(values)} values")
    return values[0], values[1]


#: The six woven fabrics of Petrak et al., Sustainability 2025, 17(4), 1388 (doi:10.3390/su17041388, CC BY 4.0):
#: weight, KES-FB measurements converted to CLO3D's parameters ((warp, weft) stretch [g/s²], shear [g/s²], (warp,
#: weft) bending [g·mm²/s²]) and the measured drape coefficient, as transcribed from the paper's tables 1, 2, 4 and 5
#: in github.com/KAFKA2306/image2outfit, config/materials/kes-woven-fabrics-2025.v1.json (``PRESET_SOURCES``).
#: name: (sample, composition and weave, weight, stretch, shear, bending, measured drape coefficient)
PETRAK2025 = {
    "polyester_twill": ("M1", "100 % polyester, twill 3/1", 135.17, (477226, 458614), 41000, (1950, 610), 0.223),
    "polyester_plain": ("M2", "100 % polyester, plain", 83.66, (471944, 373515), 46000, (850, 330), 0.228),
    "wool_blend_twill": ("M3", "75 % wool 15 % polyester 10 % elastane, twill 2/1", 178.70, (449656, 439815), 50000,
                         (2140, 2000), 0.349),
    "polyester_viscose_twill": ("M4", "63 % polyester 33 % viscose 4 % elastane, twill 2/1", 286.13, (403447, 401762),
                                61000, (2970, 2400), 0.286),
    "polyester_elastane_plain": ("M5", "97 % polyester 3 % elastane, plain", 242.00, (407166, 415023), 57000,
                                 (3220, 3880), 0.443),
    "cotton_blend_twill": ("M6", "65 % cotton 31 % polyester 4 % elastane, twill 2/1", 253.36, (473860, 404746), 126000,
                           (7430, 3700), 0.549),
}
#: Measured Cusick drape coefficients [-] of the presets that have one (the Petrak 2025 fabrics).
MEASURED_DRAPE = {name: row[6] for name, row in PETRAK2025.items()}

#: The presets by name (for scene files and the command line).
PRESETS = {"cotton": COTTON, "silk": SILK, "denim": DENIM, "rubber_sheet": RUBBER_SHEET, "denim_11oz": DENIM_11OZ,
           "cotton_polyester": COTTON_POLYESTER, "polyester": POLYESTER,
           **{name: clo_material(weight=row[2], stretch=row[3], shear=row[4], bending=row[5])
              for name, row in PETRAK2025.items()}}

#: Retardation time τ [s] of the default cloth's Kelvin-Voigt damping: kd = τ ke on every spring and hinge, so a
#: mode of angular frequency ω is damped by ζ = τω/2 (0.05 at 10⁴ rad/s, the top of a 64² cloth of a metre:
#: the grid-scale jitter dies out, the swing of the whole cloth, ζ ~ 1e-4, is left to drag).
DEFAULT_RETARDATION = 1.0e-5
#: The cloth a scene's ``[cloth]`` gets when it names no springs and no material (``io/scene_build.py``): cotton's
#: moduli (:data:`COTTON`: stretch 5e3 N/m, shear 50 N/m, bending 5e-6 N·m) with :data:`DEFAULT_RETARDATION`,
#: its areal density then taken from the table's mass (:func:`with_mass`), else cotton's 0.13 kg/m².
DEFAULT_CLOTH = ClothMaterial(stretch=COTTON.stretch, shear=COTTON.shear, bending=COTTON.bending,
                              density=COTTON.density, stretch_damping=DEFAULT_RETARDATION * COTTON.stretch,
                              bending_damping=DEFAULT_RETARDATION * COTTON.bending)


def with_mass(material: ClothMaterial, mass: float, area: float) -> ClothMaterial:
    """``material`` with the areal density that gives a cloth of ``area`` [m²] the total ``mass`` [kg]."""
    mass, area = checks.positive("cloth mass [kg]", mass), checks.positive("cloth area [m²]", area)
    return replace(material, density=mass / area)


def mesh_area(vertices, faces) -> float:
    """The total area [m²] of a triangle mesh (vertices [m], shape [v, 3]; faces, shape [t, 3])."""
    return float(_triangle_areas(_vertices(vertices), np.asarray(faces, dtype=np.int64)).sum())
_ARCSIM = "https://github.com/wxhaooo/lyra/blob/5158f74c7c92588339e19e8f86ec7f15a2a4fdf9/materials/"
_PETRAK = ("https://github.com/KAFKA2306/image2outfit/blob/1e4a63fc6ef27de3fdb6cd7b7e55e03b2fbca14f/config/materials/"
           "kes-woven-fabrics-2025.v1.json")
#: Where each preset's values come from, field by field ("none found" where no retrievable measurement was).
PRESET_SOURCES = {
    "cotton": {"all": "none found: representative values, not a measurement of one fabric"},
    "silk": {"all": "none found: representative values, not a measurement of one fabric"},
    "denim": {
        "bending, shear, stretch": "https://www.hindawi.com/journals/jtex/2016/4614168/tab5/ (fabric A, KES-F)",
        "density": "none found: 12 oz/yd², the usual weight of jeans denim; the same table's weight row reads "
                   "104 mg/cm² (1.04 kg/m²), which with its 1.07 mm thickness is 975 kg/m³, implausible for "
                   "denim, so it is not used",
    },
    "rubber_sheet": {"all": "none found: handbook values of natural rubber (E = 1.5 MPa, ν = 0.5, 930 kg/m³), "
                            "1 mm thick, not a measurement of one sheet"},
    **{name: {"all": f"Wang, O'Brien & Ramamoorthi 2011, Data-driven elastic models for cloth: modeling and measurement, "
                     f"ACM TOG 30(4):71, doi:10.1145/2010324.1964966: fabric {fabric!r}, its data as distributed with "
                     f"ARCSim (http://graphics.berkeley.edu/resources/ARCSim/), materials/{fabric}.json, e.g. {_ARCSIM}"
                     f"{fabric}.json (density; stretching, first row; bending, first column: wang2011_material)",
              "drape coefficient": "none found: the source measured no Cusick drape"}
       for name, fabric in (("denim_11oz", "11oz-black-denim"), ("cotton_polyester", "royal-target"),
                            ("polyester", "white-dots-on-blk"))},
    **{name: {"all": f"Petrak et al., Sustainability 2025, 17(4), 1388, doi:10.3390/su17041388 (CC BY 4.0): fabric "
                     f"{row[0]} ({row[1]}): weight (table 1), KES-FB measurements converted to CLO3D parameters "
                     f"(tables 2, 4), read from the transcription at {_PETRAK}; the paper itself was not retrieved "
                     f"here, so the transcription is unchecked against it",
              "drape coefficient": f"the same paper (doi:10.3390/su17041388), table 5: measured {row[6]}, via the "
                                   f"same transcription; the specimen and pedestal sizes of the measurement were not "
                                   f"retrieved"}
       for name, row in PETRAK2025.items()},
}


class GridSprings(NamedTuple):
    """Spring parameters of a regular cloth grid (:func:`grid_springs`)."""

    structural_stiffness: float  # [N/m], springs to the 4-neighbours
    shear_stiffness: float  # [N/m], springs along both diagonals of each cell
    structural_damping: float  # [N·s/m]
    shear_damping: float  # [N·s/m]


def grid_springs(material: ClothMaterial) -> GridSprings:
    """Structural and shear spring parameters of a square grid made of ``material``.

    A square lattice with structural springs k_s (length a) and springs k_d along both cell diagonals
    (length a√2) stores, per cell of area a² under an affine strain (its exact small-strain response: every
    node is a centre of symmetry),
    W = ½(k_s + k_d)(ε_xx² + ε_yy²) + k_d ε_xx ε_yy + ½ k_d γ², i.e. C11 = C22 = k_s + k_d and
    C12 = C66 = k_d in N/m, whatever the spacing a. Matching G·t = C66 and the uniaxial-stress modulus
    E·t = C11 - C12²/C11 gives::

        k_d = shear,    k_s = ½ (stretch + √(stretch² + 4 shear²)) - shear

    k_s > 0 for every positive pair, so ``shear`` > ``stretch`` needs no clamp. Central springs obey the
    Cauchy relation C12 = C66, so Poisson's ratio is not free: ν = k_d / (k_s + k_d) (≈ shear/stretch ≈ 0.01
    for woven cloth; 1/3 with k_s = 2 k_d, the only isotropic lattice, at shear = 3/8 stretch; → 1 as
    stretch/shear → 0).

    Boundary: a structural spring on the grid's outer rows and columns spans half a cell; giving it half
    the returned values makes the total stiffness exact (with full values the sheet's structural
    stiffness k_s is too high by 1/(n-1): 7 % at 16², 1.6 % at 64²). Diagonals need no correction.

    Bending is not a spring here: use the grid's crossed hinges (:func:`grid_hinges`) and no skip-one bend
    springs. Masses: :func:`grid_masses`.

    Returns:
        :class:`GridSprings`; damping kd = (stretch_damping / stretch) · ke (see the module docstring).
    """
    k_shear = material.shear
    k_structural = 0.5 * (material.stretch + math.hypot(material.stretch, 2.0 * material.shear)) - k_shear
    tau = material.stretch_damping / material.stretch
    return GridSprings(k_structural, k_shear, tau * k_structural, tau * k_shear)


def grid_masses(material: ClothMaterial, nx: int, ny: int, spacing: float, *, cells=None) -> np.ndarray:
    """Particle masses of an nx × ny grid with ``spacing`` [m]: density × the particle's dual cell.

    Interior particles carry a², edge particles a²/2, corners a²/4 (symmetric, unlike the 1/3-of-triangles
    rule of :func:`lumped_masses` on the grid's triangulation, which weighs two corners twice the others).
    With ``cells`` (a grid trimmed to a shape), each particle carries a²/4 for each present cell it touches.

    Args:
        cells: optional boolean mask of the cells present, shape [ny-1, nx-1] (cell (r, c) spans rows r, r+1
            and columns c, c+1); default all.

    Returns:
        Masses [kg], shape [ny·nx], index r·nx + c (row r, column c), summing to density·a² × the cells.
    """
    nx, ny = checks.count("nx", nx, minimum=2), checks.count("ny", ny, minimum=2)
    spacing = checks.positive("spacing", spacing)
    present = _cell_mask(cells, nx, ny)
    share = np.zeros((ny, nx))
    for dr in (0, 1):
        for dc in (0, 1):
            share[dr:dr + ny - 1, dc:dc + nx - 1] += present
    return (material.density * spacing**2 * 0.25 * share).ravel()


def _cell_mask(cells, nx: int, ny: int) -> np.ndarray:
    if cells is None:
        return np.ones((ny - 1, nx - 1), dtype=bool)
    mask = np.asarray(cells)
    if mask.shape != (ny - 1, nx - 1) or mask.dtype != bool:
        raise ConfigError(f"cells must be a boolean mask of shape [ny-1, nx-1] = [{ny - 1}, {nx - 1}], "
                          f"got {mask.dtype} {mask.shape}")
    return mask


def edge_springs(material: ClothMaterial, vertices, faces, edges) -> tuple[np.ndarray, np.ndarray]:
    """Edge-spring parameters of a triangle mesh by Van Gelder's rule (Van Gelder 1998, "Approximate
    simulation of elastic membranes by triangulated spring meshes", J. Graphics Tools 3(2)).

    Each triangle T gives each of its edges e the stiffness E·t·A_T / |e|², summed over the triangles::

        k_e = stretch · Σ_{T ∋ e} A_T / |e|²

    Derivation of the constant: the three springs of an equilateral triangle (side L, area A) store
    ½ k L² Σ_i (n_i·ε·n_i)² = ½ k L² (3/8)((tr ε)² + 2 ε:ε) (the directions are 120° apart), an isotropic
    sheet with Lamé moduli λ = μ = 3kL²/8A, hence ν = λ/(λ+2μ) = 1/3 and E·t = 8μ/3 = k L²/A: the
    constant is exactly 1. A boundary edge (one triangle) gets its triangle's share only.

    An edge network has one modulus: ν = 1/3 and G·t = 3/8 · stretch whatever ``shear`` says (woven cloth,
    G ≪ E, shears far too stiffly). E·t = stretch is kept because stretch is what a viewer sees. The rule is
    exact on equilateral triangles; on others the affine energy is exact only on average over
    orientations, and the network relaxes non-affinely (softer): see tests/test_material.py for measured
    moduli.

    Args:
        vertices: rest positions [m], shape [v, 3].
        faces: vertex indices of the triangles, shape [t, 3].
        edges: vertex pairs of the springs, shape [e, 2], each an edge of at least one face, no duplicates.

    Returns:
        ``(ke, kd)``: stiffness [N/m] and damping [N·s/m], each shape [e].
    """
    x = _vertices(vertices)
    f = _indices("faces", faces, 3, len(x))
    e = _indices("edges", edges, 2, len(x))
    area = _triangle_areas(x, f)
    sides = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    side_key, inverse = np.unique(sides[:, 0] * len(x) + sides[:, 1], return_inverse=True)
    side_area = np.bincount(inverse, weights=np.repeat(area, 3), minlength=len(side_key))
    side_key = np.append(side_key, np.iinfo(np.int64).max)  # sentinel: every search lands on a key
    ends = np.sort(e, axis=1)
    key = ends[:, 0] * len(x) + ends[:, 1]
    pos = np.searchsorted(side_key, key)
    stray = np.flatnonzero(side_key[pos] != key)
    if len(stray):
        raise ConfigError(f"edge {int(stray[0])} {e[stray[0]].tolist()} is not a side of any face "
                          f"({len(stray)} such edges): pass the mesh's own edges")
    if len(np.unique(key)) != len(key):
        raise ConfigError("edges has duplicates: each mesh edge must appear once (as [i, j] or [j, i], not both)")
    length2 = np.sum((x[e[:, 1]] - x[e[:, 0]]) ** 2, axis=1)
    short = np.flatnonzero(length2 == 0.0)
    if len(short):
        raise ConfigError(f"edge {int(short[0])} has zero length: weld or remove coincident vertices")
    ke = material.stretch * side_area[pos] / length2
    return ke, (material.stretch_damping / material.stretch) * ke


def hinge_parameters(material: ClothMaterial, vertices, hinges) -> tuple[np.ndarray, np.ndarray]:
    """Dihedral-hinge parameters of a triangle mesh (grid included), in the discrete-shells form
    (Grinspun et al. 2003, "Discrete shells"; Bridson et al. 2003)::

        k_θ = D |e|² / (A1 + A2)

    for the hinge on edge e between the triangles (x0, x1, x2) and (x0, x1, x3) of areas A1, A2.

    Derivation of the constant (1): bend a mesh of equilateral triangles (side a) into a cylinder of
    curvature κ with its axis along one edge family. The triangles between two neighbouring rows are
    coplanar, so only that family folds, each edge by θ = κh (h = a√3/2 the row spacing); such edges
    number 2/(√3 a²) per unit area and have k_θ = c·D·a²/(√3 a²/2), storing ½ c D κ² per unit area: c = 1.
    The lattice's hexagonal symmetry makes this hold for every bending direction. In discrete shells'
    notation E = k_B Σ θ² |e|/h̄_e (h̄_e a third of the mean height, |e|/h̄_e = 3|e|²/(A1+A2)), k_B = D/6.

    Every factor scales as the mesh does (θ ∝ a, hinges per area ∝ 1/a², k_θ ∝ a⁰), so the energy is
    resolution-independent; its direction dependence is the mesh's. On the regular grid (diagonal along
    (1, 1)) a cylinder whose curvature direction makes the angle φ with the x axis stores
    ½ D κ² (1 + sin 2φ + sin² 2φ): exact along rows and columns and for folds along the diagonals, 3×
    across them, 1.5× averaged over φ. On irregular Delaunay meshes the hinge energy overshoots by about
    1.2-1.6× (mesh-dependent, not resolution-dependent): dihedral-angle curvature is not consistent on
    irregular meshes (Grinspun et al. 2006, "Computing discrete shape operators on general meshes").

    Args:
        vertices: rest positions [m], shape [v, 3].
        hinges: vertex indices, shape [h, 4]: hinges[:, :2] the shared edge, hinges[:, 2] and [:, 3] the
            wing vertices.

    Returns:
        ``(k_theta, kd_theta)``: stiffness [N·m/rad] and damping [N·m·s/rad], each shape [h].
    """
    x = _vertices(vertices)
    h = _indices("hinges", hinges, 4, len(x))
    edge = x[h[:, 1]] - x[h[:, 0]]
    areas = _triangle_areas(x, h[:, [0, 1, 2]]) + _triangle_areas(x, h[:, [0, 1, 3]])
    flat = np.flatnonzero(areas == 0.0)
    if len(flat):
        raise ConfigError(f"hinge {int(flat[0])} has two triangles of zero area: remove degenerate faces")
    k_theta = material.bending * np.sum(edge**2, axis=1) / areas
    return k_theta, (material.bending_damping / material.bending) * k_theta


def grid_hinges(material: ClothMaterial, nx: int, ny: int, *, pinned=None, cells=None,
                layout: str = "crossed") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bending hinges of an nx × ny grid (particle r·nx + c at column c, row r): two crossed hinges on every
    interior row and column edge, none on the diagonals, which bend the grid as an isotropic plate.

    The hinges of the grid's own triangles (one diagonal per cell, :func:`hinge_parameters`) store, for a
    curvature tensor (A, B, C) = (κ_xx, κ_xy, κ_yy), ½ D ((A + B)² + (B + C)² + 4 B²) per unit area: a column
    edge folds by a|A + B| because its two wings sit on different rows. Bending and twist are then coupled: a
    strip free to twist (any cloth not held along its sides) relieves its bending by twisting, B = -A/5, and
    bends with 4/5 of D (measured: a D1388 cantilever's overhang, -13.0, -9.9, -8.3 % at 8, 16, 32 cells,
    tends to about the -7.2 % = 0.8^⅓ - 1 of a 0.8 D strip), and the stiffness depends on the direction
    (1 to 3 × D).

    Here each interior column edge (r, c)-(r+1, c) carries two hinges, wings (r, c-1) & (r+1, c+1) and
    (r+1, c-1) & (r, c+1), which fold by a|A + B| and a|A - B|; each row edge likewise with a|C + B| and
    a|C - B|. With k_θ = D/2 on each the energy per unit area is exactly
    ½ D/2 ((A + B)² + (A - B)² + (C + B)² + (C - B)²) = ½ D (A² + C² + 2 B²) = ½ D |κ|²:
    the isotropic plate of Poisson's ratio 0 (woven cloth's bending ν is near 0), the same in every
    direction, with twist stiffness, and independent of the spacing.

    Rigid side: a hinge whose edge and one wing are all in ``pinned`` has that wing's triangle rigid, so all of
    its fold belongs to the free half of its dual area: k_θ = D (twice). Without this a clamped edge acts as
    if it were half a cell behind the last pinned row, an error of order spacing (measured: a cantilever of
    the elastica's D1388 overhang over 4, 8, 16, 32 cells has its chord at 54.0, 48.2, 44.9, 43.2° instead of
    41.5°; with the rule 43.4, 42.0, 41.6, 41.5°, second order).

    The crossed hinges leave one mode free: the checkerboard z = ±h on alternate particles keeps both hinges of
    every edge flat, so only the springs resist it. ``layout="straight"`` has no such mode and the same energy
    for smooth bending: each interior column edge carries two straight hinges, wings (r, c-1) & (r, c+1) and
    (r+1, c-1) & (r+1, c+1), folding by a|A| each (row edges likewise by a|C|), and each cell's two diagonals a
    hinge whose wings are the cell's other corners, folding by √2 a|B|; with k_θ = D/2 on all of them the energy
    per unit area is ½ D/2 (2A² + 2C²) + 2 · ½ D/2 · 2B² = ½ D |κ|², while the checkerboard folds every
    straight hinge by 4h/a and every diagonal one by 4√2 h/a. (Measured in the settled Cusick drape at c/4:
    a checkerboard of up to 0.33 mm with the crossed hinges; analysis/drape.py.) The diagonal hinges' edges are
    never both pinned unless the whole cell is, so the rigid-side rule concerns the straight hinges only.

    Args:
        nx, ny: particles per row and per column (≥ 2).
        pinned: optional boolean mask of pinned particles, shape [ny·nx].
        cells: optional boolean mask of the cells present (see :func:`grid_masses`): an edge gets its hinges
            when both cells beside it are present; a diagonal hinge when its cell is.
        layout: "crossed" or "straight" (above).

    Returns:
        ``(hinges, k_theta, kd_theta)``: local particle indices [h, 4] (edge x0 → x1, wings x2 and x3 wound as
        the grid's faces, normals along the grid's +z), stiffness [N·m/rad] and damping [N·m·s/rad], shape [h].
    """
    nx, ny = checks.count("nx", nx, minimum=2), checks.count("ny", ny, minimum=2)
    if layout not in ("crossed", "straight"):
        raise ConfigError(f"layout must be 'crossed' or 'straight', got {layout!r}")
    g = np.arange(nx * ny).reshape(ny, nx)
    present = _cell_mask(cells, nx, ny)
    blocks = []
    straight = layout == "straight"
    if nx > 2:  # column edges (r, c) → (r+1, c), 0 < c < nx-1: wings at columns c-1 (x2) and c+1 (x3)
        x0, x1 = g[:-1, 1:-1], g[1:, 1:-1]
        both = present[:, :-1] & present[:, 1:]
        first, second = (g[:-1, 2:], g[1:, 2:]) if straight else (g[1:, 2:], g[:-1, 2:])
        blocks += [np.stack([x0, x1, g[:-1, :-2], first], -1)[both], np.stack([x0, x1, g[1:, :-2], second], -1)[both]]
    if ny > 2:  # row edges (r, c) → (r, c+1), 0 < r < ny-1: wings at rows r+1 (x2) and r-1 (x3)
        x0, x1 = g[1:-1, :-1], g[1:-1, 1:]
        both = present[:-1, :] & present[1:, :]
        first, second = (g[:-2, :-1], g[:-2, 1:]) if straight else (g[:-2, 1:], g[:-2, :-1])
        blocks += [np.stack([x0, x1, g[2:, :-1], first], -1)[both], np.stack([x0, x1, g[2:, 1:], second], -1)[both]]
    if straight:  # each cell's diagonals, wound as the faces: (r, c) → (r+1, c+1) and (r+1, c) → (r, c+1)
        blocks += [np.stack([g[:-1, :-1], g[1:, 1:], g[1:, :-1], g[:-1, 1:]], -1)[present],
                   np.stack([g[1:, :-1], g[:-1, 1:], g[1:, 1:], g[:-1, :-1]], -1)[present]]
    hinges = np.concatenate(blocks) if blocks else np.zeros((0, 4), np.int64)
    k = np.full(len(hinges), 0.5 * material.bending)
    if pinned is not None:
        fixed = np.asarray(pinned, dtype=bool).ravel()
        if fixed.shape != (nx * ny,):
            raise ConfigError(f"pinned must be a mask of nx·ny = {nx * ny} particles, got shape {fixed.shape}")
        edge = fixed[hinges[:, 0]] & fixed[hinges[:, 1]]
        rigid_side = edge & (fixed[hinges[:, 2]] ^ fixed[hinges[:, 3]])
        k[rigid_side] *= 2.0
    return hinges, k, (material.bending_damping / material.bending) * k


def lumped_masses(material: ClothMaterial, vertices, faces) -> np.ndarray:
    """Particle masses of a triangle mesh: density × one third of the area of each adjacent triangle.

    Args:
        vertices: rest positions [m], shape [v, 3].
        faces: vertex indices of the triangles, shape [t, 3].

    Returns:
        Masses [kg], shape [v], summing to density × the mesh's area.
    """
    x = _vertices(vertices)
    f = _indices("faces", faces, 3, len(x))
    share = np.repeat(_triangle_areas(x, f) / 3.0, 3)
    mass = material.density * np.bincount(f.ravel(), weights=share, minlength=len(x))
    lonely = np.flatnonzero(mass <= 0.0)
    if len(lonely):
        raise ConfigError(f"vertex {int(lonely[0])} belongs to no triangle of nonzero area ({len(lonely)} such "
                          "vertices): it would have no mass; remove unreferenced vertices and degenerate faces")
    return mass


def _triangle_areas(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Areas [m²] of the triangles x[f], shape [t]."""
    return 0.5 * np.linalg.norm(np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]), axis=1)


def _vertices(vertices) -> np.ndarray:
    x = np.asarray(vertices, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ConfigError(f"vertices must have shape [v, 3], got {x.shape}")
    if not np.isfinite(x).all():
        raise ConfigError("vertices must be finite")
    return x


def _indices(name: str, value, width: int, count: int) -> np.ndarray:
    a = np.asarray(value)
    if a.ndim != 2 or a.shape[1] != width or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise ConfigError(f"{name} must be integer vertex indices of shape [n, {width}], got {a.dtype} {a.shape}")
    if a.size and (a.min() < 0 or a.max() >= count):
        raise ConfigError(f"{name} index out of range: vertices are 0..{count - 1}, got {a.min()}..{a.max()}")
    return a.astype(np.int64)
