"""Spring materials as the builder and scene files take them: :class:`SpringMaterial` (stiffness, damping, law,
plasticity of a family of springs), the cloth's default families, and the checks that turn a family argument or a
scene's spring table into a material (:func:`spring_family`, :func:`spring_law_options`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ... import checks
from ...errors import ConfigError
from ..springs import SPRING_LAWS, SpringPlasticity, spring_law_code


@dataclass(frozen=True)
class SpringMaterial:
    """Stiffness and damping of a family of springs, and the law it follows.

    Attributes:
        ke: stiffness [N/m] (square law: [N/m²]), ≥ 0.
        kd: axial damping [N·s/m], ≥ 0.
        law: "linear" (T = ke Δ) or "square" (T = ke Δ|Δ|) at the stretch Δ (``ModelBuilder.add_springs``).
        compression_ke: the stiffness in compression (same unit as ke), ≥ 0; ``None``: ke.
        plasticity: how the springs yield and break (:class:`~warpspring.core.springs.SpringPlasticity`);
            ``None``: elastic.
    """

    ke: float
    kd: float = 0.0
    law: str = "linear"
    compression_ke: float | None = None
    plasticity: SpringPlasticity | None = None

    def spring_options(self) -> dict:
        """The law's keyword arguments of :meth:`ModelBuilder.add_springs`."""
        return dict(law=self.law, compression_stiffness=self.compression_ke, plasticity=self.plasticity)


#: Default cloth spring families (structural, shear, bend) of ``add_cloth_grid``/``add_cloth_mesh``.
DEFAULT_STRUCTURAL = SpringMaterial(ke=1.0e3, kd=1.0)
DEFAULT_SHEAR = SpringMaterial(ke=1.0e3, kd=1.0)
DEFAULT_BEND = SpringMaterial(ke=1.0e2, kd=0.1)


def spring_family(name: str, value, default: SpringMaterial) -> SpringMaterial | None:
    """A cloth's spring family argument as the builder uses it, accepting what a scene file accepts.

    Args:
        name: the family's name ("structural", "shear", "bend"), for messages.
        value: a :class:`SpringMaterial`; a mapping with ``ke`` [N/m] and/or ``kd`` [N·s/m] (each missing one is
            ``default``'s, as in a scene file's table), and optionally the law's keys (:data:`SPRING_TABLE_KEYS`);
            ``True`` (``default``); ``False`` or ``None`` (no springs of the family).
        default: the family's default material.

    Returns:
        The material, or ``None`` for a family switched off.

    Raises:
        ConfigError: any other value, an unknown key, or a stiffness or damping that is not a finite number ≥ 0.
    """
    if value is None or value is False:
        return None
    if value is True:
        return default
    if isinstance(value, SpringMaterial):
        material = value
    elif isinstance(value, Mapping):
        unknown = sorted(map(str, set(value) - {"ke", "kd", *SPRING_TABLE_KEYS}))
        if unknown:
            raise ConfigError(f"{name} springs: unknown key {unknown[0]!r}: a mapping takes 'ke' [N/m], 'kd' "
                              f"[N·s/m] and {', '.join(map(repr, SPRING_TABLE_KEYS))}")
        material = SpringMaterial(ke=value.get("ke", default.ke), kd=value.get("kd", default.kd),
                                  **spring_law_options(name, value))
    else:
        raise ConfigError(f"{name} springs must be a warpspring.SpringMaterial, a mapping {{'ke': ..., 'kd': ...}}, "
                          f"True (the default) or False (none), got {value!r}")
    checks.non_negative(f"{name} spring ke", material.ke)
    checks.non_negative(f"{name} spring kd", material.kd)
    return material


#: The keys of a spring table (a scene's ``[cloth.structural]``, a ``spring_family`` mapping) that choose its law
#: and plasticity, beyond ``ke`` and ``kd``: ``law`` ("linear" or "square"), ``compression_ke``, and the fields
#: of :class:`~warpspring.core.springs.SpringPlasticity`.
SPRING_TABLE_KEYS = ("law", "compression_ke", "yield_strain", "yield_force", "yield_rate", "hardening", "break_strain")


def spring_law_options(name: str, table: Mapping) -> dict:
    """The ``law``, ``compression_ke`` and ``plasticity`` of :class:`SpringMaterial` from a spring table's keys
    (:data:`SPRING_TABLE_KEYS`; absent ones keep their defaults), checked, with one-line errors naming ``name``."""
    options = {}
    if "law" in table:
        if not isinstance(table["law"], str):
            raise ConfigError(f"{name} springs: law must be a string, one of {', '.join(map(repr, SPRING_LAWS))}")
        spring_law_code(table["law"])
        options["law"] = table["law"]
    if "compression_ke" in table:
        options["compression_ke"] = checks.non_negative(f"{name} spring compression_ke", table["compression_ke"])
    plastic = {key: table[key] for key in SPRING_TABLE_KEYS[2:] if key in table}
    if plastic:
        try:
            options["plasticity"] = SpringPlasticity(**plastic)
        except ConfigError as exc:
            raise ConfigError(f"{name} springs: {exc}") from None
    return options
