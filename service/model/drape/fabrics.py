"""Fabric presets: the parameters a tailor would recognise, with units and sources.

Stretch limit: the strain at which the fabric stops giving (Kawabata's EMT, the extension at
500 gf/cm, is the usual laboratory figure). Membrane stiffness: the slope of the tensile curve
below that limit, force per width. Bending stiffness: the flexural rigidity (KES-FB2 B). Weight:
areal density as a shop lists it.

Sources (typical ranges; a preset sits inside them):
- [KES] S. Kawabata, *The Standardization and Analysis of Hand Evaluation*, 2nd ed., Textile
  Machinery Society of Japan, 1980 (KES-FB1 tensile EMT, LT; KES-FB2 bending B), and the
  measured shirting, suiting and knit values tabulated from it in
- [LMT] C. Luible, N. Magnenat-Thalmann, "The simulation of cloth using accurate physical
  parameters", CGIM 2008, Table 1 (woven cotton/wool/polyester: EMT 2-6 %, B 0.02-0.15
  gf cm2/cm; knitted jersey: EMT 10-40 %, B 0.01-0.05 gf cm2/cm);
- [W] areal weights: shirting poplin 100-150 g/m2, single jersey 150-200 g/m2, elastane
  (spandex) jersey 180-260 g/m2 (trade ranges, e.g. the fabric-weight entries of the
  encyclopedia article "Grammage" and mill data sheets);
- [E] elastane blends stretch 50-100 % before recovery fails (trade data sheets of
  Lycra/elastane jersey).
1 gf cm2/cm = 9.81e-5 N m (flexural rigidity per width); 1 gf/cm = 0.981 N/m.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Fabric:
    """One cloth's mechanical parameters (SI units in the field names' comments)."""
    name: str
    stretch_limit_pct: float  # % strain where the fabric stops giving (strain limiting above it)
    compress_limit_pct: float  # % in-plane compression before it buckles out of plane instead
    stretch_stiffness_n_per_m: float  # membrane stiffness (tension per width per unit strain), N/m
    bending_stiffness_nm: float  # flexural rigidity per width, N m (= N m2 / m)
    weight_g_per_m2: float  # areal density, g/m2
    friction: float  # Coulomb coefficient against skin (static ~ kinetic here)
    source: str

    @property
    def density_kg_per_m2(self) -> float:
        return self.weight_g_per_m2 * 1e-3


GF_CM2_PER_CM = 9.81e-5  # N m: KES bending rigidity unit

FABRICS: dict[str, Fabric] = {
    # shirting / suiting: barely stretches, stiff in bending
    "woven": Fabric("woven", stretch_limit_pct=3.0, compress_limit_pct=1.0, stretch_stiffness_n_per_m=2000.0,
                    bending_stiffness_nm=0.10 * GF_CM2_PER_CM, weight_g_per_m2=150.0, friction=0.5,
                    source="[KES][LMT] woven EMT 2-6 %, B 0.02-0.15 gf cm2/cm; [W] poplin 100-150 g/m2"),
    # single jersey (T-shirts): stretches a quarter, soft
    "knit": Fabric("knit", stretch_limit_pct=25.0, compress_limit_pct=3.0, stretch_stiffness_n_per_m=200.0,
                   bending_stiffness_nm=0.03 * GF_CM2_PER_CM, weight_g_per_m2=180.0, friction=0.6,
                   source="[KES][LMT] knitted EMT 10-40 %, B 0.01-0.05 gf cm2/cm; [W] jersey 150-200 g/m2"),
    # elastane jersey (leggings, sportswear): stretches over half, softest
    "stretch": Fabric("stretch", stretch_limit_pct=60.0, compress_limit_pct=5.0, stretch_stiffness_n_per_m=60.0,
                      bending_stiffness_nm=0.02 * GF_CM2_PER_CM, weight_g_per_m2=220.0, friction=0.7,
                      source="[E] elastane 50-100 %; [LMT] B ~0.02 gf cm2/cm; [W] elastane jersey 180-260 g/m2"),
}


def fabric(name_or_fabric: "str | Fabric") -> Fabric:
    """A preset by name, or the given :class:`Fabric` itself."""
    if isinstance(name_or_fabric, Fabric):
        return name_or_fabric
    try:
        return FABRICS[name_or_fabric]
    except KeyError:
        raise ValueError(f"unknown fabric {name_or_fabric!r}; one of {sorted(FABRICS)}") from None
