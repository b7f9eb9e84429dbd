"""What a test engineer knows about a damper before the dyno: its nominal charge, in
whatever unit the workshop uses, and its geometry from the datasheet.

- :func:`parse_pressure_bar` reads ``"150 psi"``, ``"10.3 bar"``, ``"1.03 MPa"``,
  ``"1030 kPa"`` (gauge, as charges are quoted) into bar gauge (SPEC §1).
- :func:`load_datasheet` reads a damper datasheet (TOML; keys, units and an example in
  ``docs/datasheet.example.toml``): the geometric constants of the force model
  (SPEC §3.3 ``a_rod``, ``v_gas``), which calibration then holds fixed instead of
  fitting them, optionally the nominal charge, and the oil volume and steel mass
  that give the thermal model's heat capacities (``c_oil``, ``c_cyl``) a physical prior,
  and the oil's two viscosities that fix how fast the observer's damping law thins with heat.

Errors are ``ValueError`` with a message that names the value, key or file at fault.
"""

from __future__ import annotations

import math
import re
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: Pressure units (case-insensitive) -> bar. All gauge: a charge is quoted above atmosphere.
PRESSURE_UNITS_BAR: dict[str, float] = {
    "bar": 1.0,
    "barg": 1.0,
    "mbar": 1e-3,
    "psi": 0.0689475729316836,  # 1 lbf/in² = 6894.757 Pa
    "psig": 0.0689475729316836,
    "pa": 1e-5,
    "kpa": 1e-2,
    "mpa": 10.0,  # megapascal (nobody charges a damper in millipascal)
}
#: Absolute units (a charge label in psia or bara, as `shocktwin import` reads them) -> bar,
#: then less one standard atmosphere.
ABSOLUTE_UNITS_BAR: dict[str, float] = {"bara": 1.0, "psia": PRESSURE_UNITS_BAR["psi"]}
ATM_BAR = 1.01325
_UNITS_HELP = "bar, mbar, psi, Pa, kPa, MPa (gauge); bara, psia (absolute)"
_PRESSURE = re.compile(r"^\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z]+)\s*$")


def parse_pressure_bar(text: str) -> float:
    """``"150 psi"`` -> 10.342… (bar gauge); an error names the value it cannot read.

    >>> round(parse_pressure_bar("150 psi"), 4), parse_pressure_bar("1.03 MPa"), parse_pressure_bar("900kPa")
    (10.3421, 10.3, 9.0)
    """
    m = _PRESSURE.match(text)
    if not m:
        raise ValueError(f"cannot read the pressure {text!r}: expected a number and a unit, "
                         f"e.g. '150 psi' or '10.3 bar' (units: {_UNITS_HELP})")
    value, unit = float(m.group(1)), m.group(2)
    if (absolute := ABSOLUTE_UNITS_BAR.get(unit.lower())) is not None:
        bar = value * absolute - ATM_BAR
    elif (factor := PRESSURE_UNITS_BAR.get(unit.lower())) is not None:
        bar = value * factor
    else:
        raise ValueError(f"unknown pressure unit {unit!r} in {text!r} (units: {_UNITS_HELP})")
    if not math.isfinite(bar) or bar <= -1.01325:
        raise ValueError(f"the pressure {text!r} is below vacuum")
    return bar


# ---------------------------------------------------------------------------------------
# Datasheet
# ---------------------------------------------------------------------------------------

#: Keys a datasheet may hold, by table: key -> (unit, meaning).
DATASHEET_KEYS: dict[str, dict[str, tuple[str, str]]] = {
    "damper": {
        "name": ("text", "model / part number, recorded in physics.json"),
        "nominal_charge": ("text with a unit", "nominal gas charge, e.g. \"150 psi\" (used when the "
                                               "command line gives none)"),
    },
    "geometry": {
        "a_rod_m2": ("m²", "piston-rod cross-section (force model a_rod)"),
        "rod_diameter_mm": ("mm", "piston-rod diameter; a_rod = π d²/4 (instead of a_rod_m2)"),
        "v_gas_m3": ("m³", "gas volume at mid-stroke (force model v_gas)"),
        "gas_volume_cm3": ("cm³", "gas volume at mid-stroke, cm³ = ml (instead of v_gas_m3)"),
    },
    "thermal": {
        "oil_volume_cm3": ("cm³", "damping-oil fill (inner tube + reservoir): c_oil = V · 860 kg/m³ · 1.9 kJ/(kg K)"),
        "steel_mass_kg": ("kg", "steel of the tubes, rod, piston and end caps (the damper without oil): "
                                "c_cyl = m · 480 J/(kg K)"),
    },
    "oil": {
        "viscosity_40c_cst": ("mm²/s", "kinematic viscosity of the damping oil at 40 °C (cSt)"),
        "viscosity_100c_cst": ("mm²/s", "kinematic viscosity at 100 °C (cSt); with the 40 °C value it "
                                        "fixes the oil's ASTM D341 (Walther) line"),
        "thermal_expansion_per_k": ("1/K", "volumetric thermal expansion of the oil (mineral oils "
                                           "6.5–7.5e-4); with [thermal] oil_volume_cm3, how much gas "
                                           "volume the heated oil takes"),
    },
}

#: Textbook properties that turn a datasheet's oil volume and steel mass into heat
#: capacities: mineral damper oil (density 850–870 kg/m³, specific heat 1.8–2.0 kJ/(kg K))
#: and carbon steel (460–500 J/(kg K)).
OIL_DENSITY_KG_M3 = 860.0
OIL_CP_J_PER_KGK = 1900.0
STEEL_CP_J_PER_KGK = 480.0


@dataclass
class Datasheet:
    """A damper datasheet: the force model's geometric constants it fixes, and what it said."""

    path: Path
    name: str | None = None
    nominal_charge: str | None = None
    #: Force-model parameters it fixes (SPEC §3.3 names, SI units).
    geometry: dict[str, float] = field(default_factory=dict)
    #: Heat capacities it implies (``c_oil``, ``c_cyl``, J/K): priors of the thermal fit.
    heat_capacities: dict[str, float] = field(default_factory=dict)
    #: How fast the oil thins at 40 °C, ``−d ln ν / dT`` (1/K), from its two viscosities
    #: (:func:`walther_coefficient_per_k`): the observer's damping law holds it (None: fitted).
    viscosity_coefficient_per_k: float | None = None
    #: How much gas volume the oil takes per kelvin above 20 °C, ``V_oil β_oil`` (m³/K), from
    #: ``[thermal] oil_volume_cm3`` and ``[oil] thermal_expansion_per_k`` (None: either is missing).
    oil_expansion_m3_per_k: float | None = None
    #: The file's tables as read (recorded in physics.json).
    values: dict[str, Any] = field(default_factory=dict)


#: What an automotive shock absorber's datasheet can say, widely: a value outside is in
#: another unit (a helper's trial: a rod diameter in metres, a gas volume in litres, a steel
#: mass in grams were taken as given, and the fit either failed without saying why or sat at
#: its bounds).
PLAUSIBLE: dict[str, tuple[float, float, str]] = {
    "a_rod_m2": (2e-5, 3e-3, "a 5–60 mm rod"),
    "rod_diameter_mm": (5.0, 60.0, "a piston rod"),
    "v_gas_m3": (5e-6, 5e-3, "5–5000 cm³ of gas"),
    "gas_volume_cm3": (5.0, 5000.0, "a damper's gas volume"),
    "oil_volume_cm3": (20.0, 5000.0, "a damper's oil fill"),
    "steel_mass_kg": (0.1, 50.0, "a damper's steel"),
}


def _positive(path: Path, table: str, key: str, value: Any) -> float:
    unit = DATASHEET_KEYS[table][key][0]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{path}: [{table}] {key} = {value!r}: expected a positive number ({unit})")
    check_plausible(f"{path}: [{table}] {key}", key, value, unit)
    return float(value)


def check_plausible(where: str, key: str, value: float, unit: str) -> None:
    """Refuses a value of ``key`` outside ``PLAUSIBLE``, asking for its unit."""
    if key in PLAUSIBLE:
        lo, hi, what = PLAUSIBLE[key]
        if not lo <= value <= hi:
            raise ValueError(f"{where} = {value!r}: {what} is {lo:g}–{hi:g} {unit}; is it in {unit}?")


def load_datasheet(path: str | Path) -> Datasheet:
    """Read and check a datasheet (see ``DATASHEET_KEYS`` and docs/datasheet.example.toml)."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path}: not valid TOML: {err}") from None
    for table, content in raw.items():
        if table not in DATASHEET_KEYS or not isinstance(content, dict):
            raise ValueError(f"{path}: unknown entry {table!r} (tables: "
                             f"{', '.join(f'[{t}]' for t in DATASHEET_KEYS)})")
        unknown = [k for k in content if k not in DATASHEET_KEYS[table]]
        if unknown:
            raise ValueError(f"{path}: unknown key {', '.join(unknown)} in [{table}] "
                             f"(known: {', '.join(DATASHEET_KEYS[table])})")
    sheet = Datasheet(path=path, values=raw)
    damper = raw.get("damper", {})
    for key in ("name", "nominal_charge"):
        if key in damper and not isinstance(damper[key], str):
            raise ValueError(f"{path}: [damper] {key} = {damper[key]!r}: expected a string")
    sheet.name = damper.get("name")
    sheet.nominal_charge = damper.get("nominal_charge")
    if sheet.nominal_charge is not None:
        try:
            parse_pressure_bar(sheet.nominal_charge)
        except ValueError as err:
            raise ValueError(f"{path}: [damper] nominal_charge: {err}") from None

    geo = raw.get("geometry", {})
    for si, alt, convert in (
        ("a_rod_m2", "rod_diameter_mm", lambda d: math.pi * (d * 1e-3) ** 2 / 4.0),
        ("v_gas_m3", "gas_volume_cm3", lambda v: v * 1e-6),
    ):
        if si in geo and alt in geo:
            raise ValueError(f"{path}: [geometry] gives both {si} and {alt}; give one")
        param = si.rsplit("_", 1)[0]  # a_rod, v_gas
        if si in geo:
            sheet.geometry[param] = _positive(path, "geometry", si, geo[si])
        elif alt in geo:
            sheet.geometry[param] = convert(_positive(path, "geometry", alt, geo[alt]))

    thermal = raw.get("thermal", {})
    if "oil_volume_cm3" in thermal:
        volume_m3 = _positive(path, "thermal", "oil_volume_cm3", thermal["oil_volume_cm3"]) * 1e-6
        sheet.heat_capacities["c_oil"] = volume_m3 * OIL_DENSITY_KG_M3 * OIL_CP_J_PER_KGK
    if "steel_mass_kg" in thermal:
        mass_kg = _positive(path, "thermal", "steel_mass_kg", thermal["steel_mass_kg"])
        sheet.heat_capacities["c_cyl"] = mass_kg * STEEL_CP_J_PER_KGK

    oil = raw.get("oil", {})
    viscosities = ("viscosity_40c_cst", "viscosity_100c_cst")
    if any(k in oil for k in viscosities):
        missing = [k for k in viscosities if k not in oil]
        if missing:
            raise ValueError(f"{path}: [oil] needs both viscosities; {', '.join(missing)} is missing")
        nu40, nu100 = (_positive(path, "oil", k, oil[k]) for k in viscosities)
        if nu100 >= nu40:
            raise ValueError(f"{path}: [oil] viscosity_100c_cst = {nu100:g} is not below viscosity_40c_cst "
                             f"= {nu40:g}: an oil thins as it heats")
        sheet.viscosity_coefficient_per_k = walther_coefficient_per_k(nu40, nu100)
    if "thermal_expansion_per_k" in oil:
        expansion = _positive(path, "oil", "thermal_expansion_per_k", oil["thermal_expansion_per_k"])
        if expansion > 5e-3:
            raise ValueError(f"{path}: [oil] thermal_expansion_per_k = {expansion:g}: liquids expand "
                             "by 1e-4 to 2e-3 per kelvin (mineral oil ≈ 7e-4); is it in 1/K?")
        if "oil_volume_cm3" in thermal:
            sheet.oil_expansion_m3_per_k = thermal["oil_volume_cm3"] * 1e-6 * expansion
        else:
            warnings.warn(f"{path}: [oil] thermal_expansion_per_k is not used without [thermal] "
                          "oil_volume_cm3 (how much oil expands); the gas volume stays fixed", stacklevel=2)
    return sheet


def walther_coefficient_per_k(nu40_cst: float, nu100_cst: float, temp_c: float = 40.0) -> float:
    """``−d ln ν / dT`` (1/K) at ``temp_c`` on the oil's viscosity–temperature line of ASTM D341
    (Walther): ``log10 log10(ν + 0.7) = A − B log10 T`` through the two datasheet viscosities
    (cSt, at 40 and 100 °C; T in kelvin).

    >>> round(walther_coefficient_per_k(15.0, 4.0), 4)   # an ISO VG 15 damper oil: 3 %/K
    0.0303
    """
    t40, t100, t = 313.15, 373.15, temp_c + 273.15
    z40, z100 = (math.log10(math.log10(nu + 0.7)) for nu in (nu40_cst, nu100_cst))
    b = (z40 - z100) / (math.log10(t100) - math.log10(t40))
    loglog = z40 - b * (math.log10(t) - math.log10(t40))
    nu = 10.0 ** (10.0 ** loglog) - 0.7
    return b * 10.0 ** loglog * (nu + 0.7) * math.log(10.0) / (t * nu)
