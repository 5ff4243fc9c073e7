"""Design of the OncoReach steerable stylet inside its plastic needle, and the loads applied to it.

Sources: Kheradmand, Yamamoto et al., "The OncoReach Stylet for Brachytherapy: Design Evaluation and Pilot
Study" (the published figures, as summarised in the project's ``reference/oncoreach.md``). Every value that is
not published is marked ASSUMED below; all of them are fields with a default, so they can be overridden.

Frame and units
---------------
The needle's own frame: base (the clamp at the template) at the origin, unactuated axis ``+z``; at roll 0 the
pulled tendon sits at ``+x`` and the rod bends in the x-z plane toward ``+x``. Lengths in the public fields
are millimetres, stiffnesses SI (N·m², N), tensions newtons. :meth:`RodDesign.sections` converts to SI for
the solvers.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal

import numpy as np

from reachplan.rod_model.errors import UnknownPresetError

Placement = Literal["tip", "mid", "base"]

#: Published tube radii (mm) and disk diameter (mm) by gauge.
_TUBE_RADII_MM: dict[int, tuple[float, float, float]] = {15: (0.533, 0.673, 1.4), 13: (0.747, 0.965, 1.95)}
#: ASSUMED plastic needle diameters (outer, inner) in mm by gauge.
_NEEDLE_DIAMETERS_MM: dict[int, tuple[float, float]] = {15: (1.83, 1.50), 13: (2.40, 2.05)}
#: The 13 ga stylet has about 4.47x the second moment of area of the 15 ga one (published).
_GAUGE_STIFFNESS_FACTOR: dict[int, float] = {15: 1.0, 13: 4.47}
#: Documented default maximum tendon tension (about 10 N on 15 ga, 14 N on 13 ga, benchtop PID setting).
_MAX_TENSION_N: dict[int, float] = {15: 10.0, 13: 14.0}


def _check_gauge(part: str, gauge: int) -> None:
    """Raise ``ValueError`` unless ``gauge`` is a built one (13 or 15)."""
    if gauge not in (13, 15):
        raise ValueError(f"{part} gauge must be 13 or 15, got {gauge}")


@dataclass(frozen=True)
class Calibration:
    """The two global, physical parameters fitted by :func:`reachplan.rod_model.calibrate.calibrate`.

    The defaults are the fitted values (see :mod:`reachplan.rod_model.calibrate`).

    Parameters
    ----------
    joint_stiffness_scale : float
        Effective bending stiffness of the joint section *inside the needle*, as a fraction of the measured
        free-space value ``K_bt,joints = 0.0008 N·m²`` (15 ga). Ball joints have no elastic bending
        stiffness of their own; the measured value comes from the tendons' pre-load and friction, which the
        needle's wall takes over once the stylet is inside.
    tube_arm_fraction : float
        Moment arm of a tendon inside the nitinol tube, as a fraction of the tube's inner radius. In the tube
        a tendon is not held in a channel (as it is in the disks); it shares the lumen with the other three.

    Raises
    ------
    ValueError
        ``joint_stiffness_scale`` outside (0, 10] or ``tube_arm_fraction`` outside [0, 1].
    """

    joint_stiffness_scale: float = 0.1181
    tube_arm_fraction: float = 0.6088

    def __post_init__(self) -> None:
        if not (0.0 < self.joint_stiffness_scale <= 10.0):
            raise ValueError(f"joint_stiffness_scale must be in (0, 10], got {self.joint_stiffness_scale}")
        if not (0.0 <= self.tube_arm_fraction <= 1.0):
            raise ValueError(f"tube_arm_fraction must be in [0, 1], got {self.tube_arm_fraction}")


@dataclass(frozen=True)
class NeedleSpec:
    """The plastic interstitial needle (tube 2 of the two-tube model).

    Lengths in mm, moduli in Pa, as in the reference.

    Parameters
    ----------
    gauge : int
        13 or 15.
    outer_diameter_mm, inner_diameter_mm : float
        ASSUMED: 15 ga 1.83 / 1.50 mm, 13 ga 2.40 / 2.05 mm.
    young_modulus_pa, shear_modulus_pa : float
        Published: 3.2 GPa and 1.06 GPa.
    density_kg_m3 : float
        ASSUMED 1410 kg/m³ (acetal); only used for a gravity load.

    Raises
    ------
    ValueError
        Another gauge, ``inner_diameter_mm`` not in (0, ``outer_diameter_mm``), or a non-positive modulus or
        density.
    """

    gauge: int
    outer_diameter_mm: float
    inner_diameter_mm: float
    young_modulus_pa: float = 3.2e9
    shear_modulus_pa: float = 1.06e9
    density_kg_m3: float = 1410.0

    def __post_init__(self) -> None:
        _check_gauge("needle", self.gauge)
        if not (0.0 < self.inner_diameter_mm < self.outer_diameter_mm):
            raise ValueError("needle diameters must satisfy 0 < inner_diameter_mm < outer_diameter_mm")
        if self.young_modulus_pa <= 0 or self.shear_modulus_pa <= 0 or self.density_kg_m3 <= 0:
            raise ValueError("needle moduli and density must be positive")

    @classmethod
    def for_gauge(cls, gauge: int) -> NeedleSpec:
        """Build the needle of ``gauge`` (13 or 15) with its ASSUMED default diameters; ValueError otherwise."""
        if gauge not in _NEEDLE_DIAMETERS_MM:
            raise ValueError(f"needle gauge must be 13 or 15, got {gauge}")
        od, id_ = _NEEDLE_DIAMETERS_MM[gauge]
        return cls(gauge, od, id_)

    @property
    def area_m2(self) -> float:
        """Cross-section area in m²."""
        return math.pi / 4 * (self.outer_diameter_mm**2 - self.inner_diameter_mm**2) * 1e-6

    @property
    def second_moment_m4(self) -> float:
        """Second moment of area in m⁴."""
        return math.pi / 64 * (self.outer_diameter_mm**4 - self.inner_diameter_mm**4) * 1e-12


@dataclass(frozen=True)
class StyletDesign:
    """The steerable stylet (tube 1): a nitinol tube with a section of ball joints and routing disks.

    Parameters
    ----------
    gauge : int
        13 or 15 (sets the tube radii and disk diameter below when built with :meth:`for_gauge`).
    n_joints : int
        Number of spherical joints (15, 20, 30 were built).
    placement : {"tip", "mid", "base"}
        Where the joint section sits; ignored when ``joint_start_mm`` is given.
    joint_start_mm : float or None
        Explicit arc length (from the base) where the joint section starts.
    asymmetric : bool
        Asymmetric disk: one tendon channel, ball offset to the other side, larger moment arm.
    tendon_angles_deg : tuple of float
        Angular position of each tendon around the axis, measured from ``+x`` toward ``+y`` (1-4 tendons).
        Default: the four channels of the symmetric disk; one channel for the asymmetric disk.
    length_mm : float
        Stylet length = free needle length, ASSUMED 200 mm.
    joint_pitch_mm : float
        Length per joint: a 20-joint section is about 33 mm (published), so 1.65 mm.
    tube_inner_radius_mm, tube_outer_radius_mm, disk_diameter_mm : float
        Published per gauge.
    tube_young_modulus_pa, tube_shear_modulus_pa : float
        Nitinol, published: 68 GPa, 25.5 GPa.
    joint_bending_stiffness_nm2, joint_torsion_stiffness_nm2 : float
        Measured (15 ga) 0.0008 and 0.0047 N·m²; 13 ga ASSUMED x4.47 (the tube's ratio of second moments).
    disk_arm_mm : float
        Tendon moment arm inside the disks. ASSUMED 0.42 mm for the 15 ga symmetric disk (inside the 1.4 mm
        disk), scaled with the disk diameter for 13 ga, x1.5 for the asymmetric disk.
    calibration : Calibration
        The two fitted global parameters.
    tendon_friction_coefficient : float
        Capstan (Coulomb) friction coefficient of a tendon on its routing (tube lumen and disk channels): the
        tension decays as ``exp(−μ φ)`` with the wrap angle ``φ`` accumulated along the bent routing while
        the tendon is pulled, and grows so while it is released (capstan law; tendon-sheath hysteresis as in
        Kaneko et al., IEEE T-RA 1991, and Do et al., Mechatronics 2015). Default 0 until calibrated: the
        published calibration subset has no unloading data to separate it from the moment arm.
    joint_friction_coefficient : float
        Coulomb coefficient at the ball-disk contacts of the joint section: a friction moment
        ``μ_j × ball radius × stack compression`` (the compression is the local tendon tension) opposes any
        change of the joint curvature. Default 0 until calibrated (the paper blames joint friction for its
        base-placement error but publishes no coefficient).
    ball_diameter_mm : float
        Diameter of the steel balls between the disks, published 0.8 mm.

    Raises
    ------
    ValueError
        Another gauge, no joints, an unknown placement, 0 or more than 4 tendons (more than 1 on the asymmetric
        disk), tube radii out of order, a non-positive length, modulus, stiffness or arm, a disk arm outside
        the disk, a joint section that does not fit in the stylet, or a negative friction coefficient.
    """

    gauge: int
    n_joints: int
    placement: Placement = "tip"
    joint_start_mm: float | None = None
    asymmetric: bool = False
    tendon_angles_deg: tuple[float, ...] = (0.0, 90.0, 180.0, 270.0)
    length_mm: float = 200.0
    joint_pitch_mm: float = 1.65
    tube_inner_radius_mm: float = 0.533
    tube_outer_radius_mm: float = 0.673
    disk_diameter_mm: float = 1.4
    tube_young_modulus_pa: float = 68e9
    tube_shear_modulus_pa: float = 25.5e9
    joint_bending_stiffness_nm2: float = 0.0008
    joint_torsion_stiffness_nm2: float = 0.0047
    disk_arm_mm: float = 0.42
    calibration: Calibration = field(default_factory=Calibration)
    tendon_friction_coefficient: float = 0.0
    joint_friction_coefficient: float = 0.0
    ball_diameter_mm: float = 0.8

    def __post_init__(self) -> None:
        _check_gauge("stylet", self.gauge)
        if not (0.0 <= self.tendon_friction_coefficient <= 2.0 and 0.0 <= self.joint_friction_coefficient <= 2.0):
            raise ValueError("friction coefficients must be in [0, 2]")
        if not (0.0 < self.ball_diameter_mm < self.disk_diameter_mm):
            raise ValueError("ball_diameter_mm must be positive and smaller than the disk")
        if self.n_joints < 1:
            raise ValueError(f"n_joints must be at least 1, got {self.n_joints}")
        if self.placement not in ("tip", "mid", "base"):
            raise ValueError(f"placement must be 'tip', 'mid' or 'base', got {self.placement!r}")
        if not (1 <= len(self.tendon_angles_deg) <= 4):
            raise ValueError(f"a stylet has 1 to 4 tendons, got {len(self.tendon_angles_deg)}")
        if self.asymmetric and len(self.tendon_angles_deg) != 1:
            raise ValueError("the asymmetric disk has exactly one tendon channel")
        if not (0.0 < self.tube_inner_radius_mm < self.tube_outer_radius_mm):
            raise ValueError("tube radii must satisfy 0 < tube_inner_radius_mm < tube_outer_radius_mm")
        positive = (self.length_mm, self.joint_pitch_mm, self.disk_diameter_mm, self.tube_young_modulus_pa,
                    self.tube_shear_modulus_pa, self.joint_bending_stiffness_nm2,
                    self.joint_torsion_stiffness_nm2, self.disk_arm_mm)
        if min(positive) <= 0:
            raise ValueError("lengths, moduli, stiffnesses and the disk arm must be positive")
        if self.disk_arm_mm >= self.disk_diameter_mm / 2:
            raise ValueError(f"disk_arm_mm {self.disk_arm_mm} must lie inside the disk (radius "
                             f"{self.disk_diameter_mm / 2} mm)")
        start, end = self.joint_span_mm
        if start < 0 or end > self.length_mm + 1e-9:
            raise ValueError(f"joint section [{start:.2f}, {end:.2f}] mm does not fit in the {self.length_mm} mm "
                             "stylet; shorten it or move joint_start_mm")

    @classmethod
    def for_gauge(cls, gauge: int, n_joints: int = 20, placement: Placement = "tip", *,
                  asymmetric: bool = False, calibration: Calibration | None = None) -> StyletDesign:
        """Build a stylet with the published (and ASSUMED default) values of ``gauge``.

        Parameters
        ----------
        gauge : int
            13 or 15.
        n_joints : int
            Number of spherical joints.
        placement : {"tip", "mid", "base"}
            Where the joint section sits.
        asymmetric : bool
            The asymmetric disk (one tendon, moment arm x1.5).
        calibration : Calibration, optional
            Default: the fitted values.

        Raises
        ------
        ValueError
            Another gauge, or a design that does not validate (see the class docstring).
        """
        if gauge not in _TUBE_RADII_MM:
            raise ValueError(f"stylet gauge must be 13 or 15, got {gauge}")
        r_in, r_out, disk = _TUBE_RADII_MM[gauge]
        k = _GAUGE_STIFFNESS_FACTOR[gauge]
        arm = 0.42 * disk / 1.4 * (1.5 if asymmetric else 1.0)
        return cls(gauge=gauge, n_joints=n_joints, placement=placement, asymmetric=asymmetric,
                   tendon_angles_deg=(0.0,) if asymmetric else (0.0, 90.0, 180.0, 270.0),
                   tube_inner_radius_mm=r_in, tube_outer_radius_mm=r_out, disk_diameter_mm=disk,
                   joint_bending_stiffness_nm2=0.0008 * k, joint_torsion_stiffness_nm2=0.0047 * k,
                   disk_arm_mm=arm, calibration=calibration or Calibration())

    @property
    def joint_length_mm(self) -> float:
        """Length of the joint section in mm."""
        return self.n_joints * self.joint_pitch_mm

    @property
    def joint_span_mm(self) -> tuple[float, float]:
        """(start, end) arc length of the joint section from the base, mm."""
        lj = self.joint_length_mm
        if self.joint_start_mm is not None:
            start = self.joint_start_mm
        else:
            start = {"tip": self.length_mm - lj, "mid": (self.length_mm - lj) / 2, "base": 0.0}[self.placement]
        return start, start + lj

    @property
    def tube_arm_mm(self) -> float:
        """Calibrated tendon moment arm inside the nitinol tube, mm."""
        return self.calibration.tube_arm_fraction * self.tube_inner_radius_mm

    @property
    def tube_area_m2(self) -> float:
        """Cross-section area of the nitinol tube, m²."""
        return math.pi * (self.tube_outer_radius_mm**2 - self.tube_inner_radius_mm**2) * 1e-6

    @property
    def tube_bending_stiffness_nm2(self) -> float:
        """E·I of the nitinol tube, N·m²."""
        i = math.pi / 4 * (self.tube_outer_radius_mm**4 - self.tube_inner_radius_mm**4) * 1e-12
        return self.tube_young_modulus_pa * i

    @property
    def tube_torsion_stiffness_nm2(self) -> float:
        """G·J of the nitinol tube, N·m²."""
        j = math.pi / 2 * (self.tube_outer_radius_mm**4 - self.tube_inner_radius_mm**4) * 1e-12
        return self.tube_shear_modulus_pa * j


@dataclass(frozen=True)
class Section:
    """One stretch of constant properties along the rod (SI units, for the solvers).

    Parameters
    ----------
    start_m, end_m : float, m
        Arc length from the base where the stretch starts and ends.
    kind : str
        ``"tube"`` or ``"joints"``.
    ei1, gj1, ea1, ga1 : float, N·m², N·m², N, N
        The stylet's bending, torsion, axial and shear stiffness.
    ei2, gj2, ea2, ga2 : float, N·m², N·m², N, N
        The needle's.
    arm_m : float, m
        The tendon moment arm (disk arm in the joints, calibrated tube arm in the tube).
    capstan_mu : float
        The tendon's friction coefficient on its routing.
    joint_friction_arm_m : float, m
        The joints' Coulomb coefficient × ball radius (0 in a tube section).
    """

    start_m: float
    end_m: float
    kind: str
    ei1: float
    gj1: float
    ea1: float
    ga1: float
    ei2: float
    gj2: float
    ea2: float
    ga2: float
    arm_m: float
    capstan_mu: float = 0.0
    joint_friction_arm_m: float = 0.0

    @property
    def length_m(self) -> float:
        """Section length, m."""
        return self.end_m - self.start_m


@dataclass(frozen=True)
class RodDesign:
    """A stylet in a needle: what every rod model solves.

    Frozen and hashable: the planner caches curvature tables and shape banks per design.

    Parameters
    ----------
    name : str
        Preset name or a user label.
    stylet : StyletDesign
        The steerable stylet (tube 1).
    needle : NeedleSpec
        The plastic needle it runs in (tube 2), same gauge.
    max_tension_n : float
        Largest tendon tension the design is meant for (documented default: 10 N on 15 ga, 14 N on 13 ga,
        the published benchtop settings). The planner should not ask for more.

    Raises
    ------
    ValueError
        Stylet and needle of different gauges, a disk that does not fit in the needle's lumen, or
        ``max_tension_n`` outside (0, 100] N.
    """

    name: str
    stylet: StyletDesign
    needle: NeedleSpec
    max_tension_n: float

    def __post_init__(self) -> None:
        if self.stylet.gauge != self.needle.gauge:
            raise ValueError(f"stylet gauge {self.stylet.gauge} does not match needle gauge {self.needle.gauge}")
        if self.stylet.disk_diameter_mm >= self.needle.inner_diameter_mm:
            raise ValueError(f"disk diameter {self.stylet.disk_diameter_mm} mm does not fit in the needle's "
                             f"{self.needle.inner_diameter_mm} mm lumen")
        if not (0.0 < self.max_tension_n <= 100.0):
            raise ValueError(f"max_tension_n must be in (0, 100] N, got {self.max_tension_n}")

    @property
    def length_mm(self) -> float:
        """Free length of stylet and needle, mm."""
        return self.stylet.length_mm

    @property
    def n_tendons(self) -> int:
        """Number of tendons."""
        return len(self.stylet.tendon_angles_deg)

    def tendon_unit_offsets(self, roll_deg: float = 0.0) -> np.ndarray:
        """Return the unit direction of each tendon's offset from the axis, rolled by ``roll_deg`` degrees.

        Returns
        -------
        (k, 3) float, stylet body frame
            One row per tendon, in the order of ``StyletDesign.tendon_angles_deg``; z component 0.
        """
        a = np.radians(np.asarray(self.stylet.tendon_angles_deg, dtype=float) + roll_deg)
        return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)

    def sections(self) -> tuple[Section, ...]:
        """Split the rod into stretches of constant properties, base to tip (SI units; cached)."""
        return _sections(self)

    def loads(self, tension_n: float, roll_deg: float = 0.0, history: TensionHistory | None = None) -> Loads:
        """Return free-space loads pulling tendon 0 (the one at ``+x`` at roll 0) with ``tension_n`` newtons."""
        return Loads(tensions_n=(tension_n,) + (0.0,) * (self.n_tendons - 1), roll_deg=roll_deg,
                     history=history or TensionHistory())

    @property
    def has_friction(self) -> bool:
        """True when a friction coefficient is non-zero."""
        return self.stylet.tendon_friction_coefficient > 0 or self.stylet.joint_friction_coefficient > 0


@lru_cache(maxsize=256)
def _sections(design: RodDesign) -> tuple[Section, ...]:
    st, nd = design.stylet, design.needle
    ei2 = nd.young_modulus_pa * nd.second_moment_m4
    gj2 = nd.shear_modulus_pa * 2 * nd.second_moment_m4
    ea2 = nd.young_modulus_pa * nd.area_m2
    ga2 = nd.shear_modulus_pa * nd.area_m2
    # ASSUMED: the chain of balls is axially and in shear as stiff as the tube (balls in contact).
    ea1 = st.tube_young_modulus_pa * st.tube_area_m2
    ga1 = st.tube_shear_modulus_pa * st.tube_area_m2
    mu = st.tendon_friction_coefficient
    tube = (st.tube_bending_stiffness_nm2, st.tube_torsion_stiffness_nm2, ea1, ga1, ei2, gj2, ea2, ga2,
            st.tube_arm_mm * 1e-3, mu, 0.0)
    joints = (st.joint_bending_stiffness_nm2 * st.calibration.joint_stiffness_scale,
              st.joint_torsion_stiffness_nm2, ea1, ga1, ei2, gj2, ea2, ga2, st.disk_arm_mm * 1e-3, mu,
              st.joint_friction_coefficient * st.ball_diameter_mm / 2 * 1e-3)
    a, b = st.joint_span_mm
    spans = [(0.0, a, "tube", tube), (a, b, "joints", joints), (b, st.length_mm, "tube", tube)]
    return tuple(Section(s0 * 1e-3, s1 * 1e-3, kind, *props) for s0, s1, kind, props in spans if s1 - s0 > 1e-9)


def _vec3(v: tuple[float, float, float] | np.ndarray, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be three finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True, eq=False)
class Foundation:
    """An elastic foundation holding the rod (tissue around an inserted needle), tied to a track.

    Parameters
    ----------
    s_mm : (m,) float, mm, increasing
        Arc lengths (from the solve's base) of the nodes; values are linear between nodes, constant beyond.
    stiffness_n_per_mm2 : (m,) float, N/mm per mm of rod
        Winkler modulus ``k`` of the medium at each node (0: no tissue there).
    track_mm : (m, 3) float, mm, base frame
        Rest position of the tissue at each node (where the tip cut it).
    slip_mm : (m,) float, mm
        Lateral offset beyond which the tissue gives way: the force per length is capped at ``k·slip``.

    The force per length on the rod is ``−k δ`` with ``δ`` the centreline's offset from the track point at the
    same arc length, perpendicular to the rod's tangent (the rod slides freely along its track).
    """

    s_mm: np.ndarray
    stiffness_n_per_mm2: np.ndarray
    track_mm: np.ndarray
    slip_mm: np.ndarray

    def __post_init__(self) -> None:
        s = np.array(self.s_mm, dtype=float)
        k = np.array(self.stiffness_n_per_mm2, dtype=float)
        tr = np.array(self.track_mm, dtype=float)
        sl = np.array(self.slip_mm, dtype=float)
        m = len(s)
        if (s.ndim != 1 or m < 1 or k.shape != (m,) or tr.shape != (m, 3) or sl.shape != (m,)
                or np.any(np.diff(s) <= 0)):
            raise ValueError("foundation: s_mm (m,) increasing, stiffness (m,), track (m, 3), slip (m,)")
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(s)) and np.all(k >= 0) and np.all(sl > 0)
                and np.all(np.isfinite(k)) and np.all(np.isfinite(sl))):
            raise ValueError("foundation: values must be finite, stiffness >= 0 and slip > 0")
        for name, a in (("s_mm", s), ("stiffness_n_per_mm2", k), ("track_mm", tr), ("slip_mm", sl)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def packed_si(self) -> np.ndarray:
        """(6m,) float, SI: the kernel's layout ``s, k, track (3), slip`` per node (m, N/m², m, m)."""
        return np.column_stack([self.s_mm * 1e-3, self.stiffness_n_per_mm2 * 1e6, self.track_mm * 1e-3,
                                self.slip_mm * 1e-3]).ravel()


@dataclass(frozen=True)
class TensionHistory:
    """Where a quasi-static tension sweep comes from (only matters with friction, see :class:`StyletDesign`).

    Parameters
    ----------
    increasing : bool
        The tendon is being pulled (True) or released (False).
    reversal_tension_n : float
        Load-cell tension of tendon 0 at the last reversal of the sweep (the peak before a release, the
        valley before a pull), N; 0 for a first pull from rest.
    reversal_joint_curvature_per_m : float
        Curvature of the joint section at that reversal, 1/m (where friction holds the joints).
    """

    increasing: bool = True
    reversal_tension_n: float = 0.0
    reversal_joint_curvature_per_m: float = 0.0

    def __post_init__(self) -> None:
        if not (self.reversal_tension_n >= 0 and self.reversal_joint_curvature_per_m >= 0
                and math.isfinite(self.reversal_tension_n) and math.isfinite(self.reversal_joint_curvature_per_m)):
            raise ValueError("reversal tension and curvature must be finite and non-negative")


@dataclass(frozen=True)
class Loads:
    """Loads on the rod, in the needle's base frame (``+z`` unactuated axis).

    Parameters
    ----------
    tensions_n : tuple of float
        Tension of each tendon (N, ≥ 0), in the order of ``StyletDesign.tendon_angles_deg``.
    roll_deg : float
        Roll of the stylet about its axis at the base: rotates every tendon (and so the bending plane)
        from ``+x`` toward ``+y``.
    tip_force_n : (3,) float, N, base frame
        External force on the needle tip.
    tip_moment_nm : (3,) float, N·m, base frame
        External moment on the needle tip.
    distributed_n_per_m : (3,) float, N/m, base frame
        Uniform distributed force on the needle (e.g. gravity: ``rho * A * g``).
    history : TensionHistory
        Pulling from rest by default; a release or a second pull for the hysteresis of a friction model.
    foundation : Foundation or None
        Elastic medium holding the rod (an external load).

    Raises
    ------
    ValueError
        No tension, a negative or non-finite tension, a non-finite roll, or a vector that is not three finite
        numbers.
    """

    tensions_n: tuple[float, ...]
    roll_deg: float = 0.0
    tip_force_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_moment_nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distributed_n_per_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    history: TensionHistory = TensionHistory()
    foundation: Foundation | None = None

    def __post_init__(self) -> None:
        t = tuple(float(x) for x in self.tensions_n)
        if not t or not all(math.isfinite(x) and x >= 0 for x in t):
            raise ValueError(f"tensions_n must be one or more finite non-negative values, got {self.tensions_n!r}")
        if not math.isfinite(self.roll_deg):
            raise ValueError("roll_deg must be finite")
        object.__setattr__(self, "tensions_n", t)
        object.__setattr__(self, "tip_force_n", _vec3(self.tip_force_n, "tip_force_n"))
        object.__setattr__(self, "tip_moment_nm", _vec3(self.tip_moment_nm, "tip_moment_nm"))
        object.__setattr__(self, "distributed_n_per_m", _vec3(self.distributed_n_per_m, "distributed_n_per_m"))

    @property
    def has_external(self) -> bool:
        """True when any external force or moment is applied."""
        return self.foundation is not None or any(
            any(v) for v in (self.tip_force_n, self.tip_moment_nm, self.distributed_n_per_m))


def gravity_load(design: RodDesign,
                 direction: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> tuple[float, float, float]:
    """Compute the distributed weight of the needle along ``direction``.

    Parameters
    ----------
    design : RodDesign
        Its needle's density and cross-section give the weight per length.
    direction : (3,) float, base frame
        Direction of gravity; normalised here.

    Returns
    -------
    (3,) float, N/m, base frame
        For :attr:`Loads.distributed_n_per_m`.
    """
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    w = design.needle.density_kg_m3 * design.needle.area_m2 * 9.80665
    return _vec3(w * d, "gravity")


#: The named presets (the configurations built and measured in the paper, plus variants).
PRESET_NAMES: tuple[str, ...] = ("15ga-20j-tip", "13ga-20j-tip", "15ga-30j-tip", "15ga-15j-tip", "15ga-20j-mid",
                                 "15ga-20j-base", "15ga-20j-asym", "13ga-30j-tip")

_PRESET_RE = re.compile(r"^(13|15)ga-(\d+)j-(tip|mid|base|asym)$")


def preset(name: str, calibration: Calibration | None = None) -> RodDesign:
    """Build the design called ``name``.

    Names follow ``{13|15}ga-{joints}j-{tip|mid|base|asym}`` (``asym``: asymmetric disk at the tip), e.g.
    ``15ga-20j-tip``; :data:`PRESET_NAMES` lists the usual ones.

    Parameters
    ----------
    name : str
        The preset name.
    calibration : Calibration, optional
        Default: the fitted values.

    Raises
    ------
    UnknownPresetError
        When the name does not follow that pattern or the joint section does not fit.
    """
    m = _PRESET_RE.match(name)
    if m is None:
        raise UnknownPresetError(f"unknown preset {name!r}; use {{13|15}}ga-<joints>j-{{tip|mid|base|asym}}, e.g. "
                                 f"{', '.join(PRESET_NAMES)}")
    gauge, joints, where = int(m.group(1)), int(m.group(2)), m.group(3)
    placement: Placement = "tip" if where == "asym" else where  # type: ignore[assignment]
    try:
        stylet = StyletDesign.for_gauge(gauge, joints, placement, asymmetric=where == "asym",
                                        calibration=calibration)
    except ValueError as exc:
        raise UnknownPresetError(f"preset {name!r} is not a valid design: {exc}") from None
    return RodDesign(name, stylet, NeedleSpec.for_gauge(gauge), _MAX_TENSION_N[gauge])
