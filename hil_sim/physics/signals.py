"""Transducer waveforms for one laser shot: OA (one way) and US (round trip) arrivals, noise, ADC.

Every waveform holds what one laser pulse produces (paper §III-1): the transmitter's direct
coupling ("bang") at the start, the optoacoustic arrival at t0_OA + d/c when the surface
absorbs light, and the ultrasound echo at t0_US + 2d/c when it reflects sound. Materials set
amplitude, spectrum, wall ringing and availability. The sensor's own numbers are not published;
every default here is a documented assumption (docs/sim.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .scene import Hit, keyed_laplace, keyed_normal


def speed_of_sound_mm_us(temperature_c: float) -> float:
    """Speed of sound in dry air, c = 331.3 sqrt(1 + T/273.15) m/s, in mm/us."""
    return 0.3313 * np.sqrt(1.0 + temperature_c / 273.15)


@dataclass(frozen=True)
class Material:
    """Acoustic and optical behaviour of one material (amplitudes: the received pulse's peak in
    ADC counts at 10 mm; oa_fc_mhz/oa_bw: the emitted OA pulse, before the receive chain)."""

    oa: bool                 # absorbs the laser: an OA arrival exists (not transparent/mirror)
    us: bool                 # reflects sound: a US echo exists (not porous)
    oa_amp: float = 3000.0
    oa_fc_mhz: float = 1.2   # centre frequency of the OA pulse (absorption depth)
    oa_bw: float = 0.8       # fractional bandwidth
    us_amp: float = 6000.0
    us_fc_scale: float = 1.0  # echo spectrum shift (surface roughness low-passes it)
    ring_fc_mhz: float = 0.0  # wall resonance of thin or hollow objects (0: solid)
    ring_gain: float = 0.0
    ring_decay_us: float = 3.0
    variability: float = 0.05  # per-shot spread of amplitude and spectrum
    roughness_oa_mm: float = 0.06  # surface/spot range scatter, Laplace scale (OA)
    roughness_us_mm: float = 0.19  # Gaussian sigma (US)
    c_mm_us: float = 0.0      # speed of sound inside (mm/us); 0: sound does not cross it
    us_through: float = 0.0   # share of an echo's amplitude left after crossing it there and
    #                          back (an interface behind it: a wall's inner side, a liquid)


#: defaults; apple is deliberately close to plastic but far more variable (paper Fig. 5). The
#: OA centre frequencies are the emitted ones, chosen so that the received centres (after the
#: receive chain, `received`) stay where the materials were tuned: aluminium 1.1 MHz, plastic
#: 0.9, apple 0.85, paper 0.7, foam 0.5 (graphite's 1.6 MHz cannot pass the band: 1.14)
MATERIALS: dict[str, Material] = {
    "graphite": Material(oa=True, us=True, oa_amp=9000, oa_fc_mhz=1.6, us_amp=1500,
                         variability=0.05),
    "aluminium": Material(oa=True, us=True, oa_amp=2500, oa_fc_mhz=1.24, us_amp=7000,
                          ring_fc_mhz=0.55, ring_gain=0.25, ring_decay_us=6.0,
                          c_mm_us=6.32, us_through=0.08),
    "steel": Material(oa=False, us=True, us_amp=7500, ring_fc_mhz=0.75, ring_gain=0.35,
                      ring_decay_us=8.0, c_mm_us=5.9, us_through=0.06),
    "glass": Material(oa=False, us=True, us_amp=6500, us_fc_scale=1.05, ring_fc_mhz=0.9,
                      ring_gain=0.5, ring_decay_us=5.0, c_mm_us=5.64, us_through=0.1),
    "plastic": Material(oa=True, us=True, oa_amp=3500, oa_fc_mhz=0.84, us_amp=4500,
                        us_fc_scale=0.95, ring_fc_mhz=0.35, ring_gain=0.15, ring_decay_us=2.0,
                        variability=0.10, c_mm_us=2.4, us_through=0.15),
    "apple": Material(oa=True, us=True, oa_amp=3200, oa_fc_mhz=0.77, us_amp=4000,
                      us_fc_scale=0.9, ring_fc_mhz=0.35, ring_gain=0.12, ring_decay_us=1.5,
                      variability=0.30, c_mm_us=1.5, us_through=0.05),
    "paper": Material(oa=True, us=True, oa_amp=4000, oa_fc_mhz=0.60, us_amp=3000,
                      us_fc_scale=0.8, variability=0.12, c_mm_us=1.2, us_through=0.2),
    "foam": Material(oa=True, us=False, oa_amp=2000, oa_fc_mhz=0.39, oa_bw=1.0,
                     variability=0.15),
    # a liquid filling a container (never a surface facing the air: it has no OA, and it
    # transmits sound well); its echoes are those of the walls it touches
    "water": Material(oa=False, us=True, us_amp=3000, c_mm_us=1.48, us_through=0.9,
                      variability=0.05),
}


@dataclass
class SensorModel:
    """The transducer chain: delays, pulse shapes, noise and the ADC (counts)."""

    temperature_c: float = 20.0
    t0_oa_us: float = 2.0     # trigger-to-OA-emission delay (electronics, transducer)
    t0_us_us: float = 4.0     # trigger-to-US-emission delay (laser-driven transmitter)
    us_fc_mhz: float = 1.0    # transducer centre frequency
    us_bw: float = 0.6        # fractional -6 dB bandwidth of the pulse-echo (two-way) chain
    aa_cutoff_mhz: float = 1.25  # front end's anti-alias low-pass, -3 dB (Gaussian, linear phase)
    bang_amp: float = 2500.0  # transmitter direct coupling at t0_US
    bang_decay_us: float = 2.0
    spread_mm: float = 20.0   # amplitude ~ 1 / (1 + d / spread_mm)
    us_angle_deg: float = 12.0  # US echo falls as exp(-(angle / us_angle)^2): specular
    noise_counts: float = 20.0
    spike_prob: float = 0.002   # interference spikes per shot
    spike_amp: float = 6000.0
    baseline: float = 32768.0
    materials: dict[str, Material] = field(default_factory=lambda: dict(MATERIALS))

    @property
    def c_mm_us(self) -> float:
        """Speed of sound at the model's air temperature (mm/us)."""
        return speed_of_sound_mm_us(self.temperature_c)


FWHM = 2 * np.sqrt(2 * np.log(2))  # -6 dB full width of a Gaussian amplitude spectrum / sigma


def through(fc: float, bw: float, pass_fc: float, pass_sigma: float) -> tuple[float, float]:
    """(centre MHz, fractional -6 dB bandwidth) of a Gaussian-modulated pulse (fc MHz, bw)
    after a Gaussian pass band centred at pass_fc with std pass_sigma (MHz; pass_fc = 0: a
    low-pass). A product of Gaussian spectra is Gaussian, so the received pulse keeps the
    form: exactly through a low-pass, and through a band pass up to the pulse's two spectral
    lobes meeting at 0 Hz (under 0.5 % of the peak for the materials' pulses)."""
    sig = bw * fc / FWHM
    centre = (fc * pass_sigma ** 2 + pass_fc * sig ** 2) / (sig ** 2 + pass_sigma ** 2)
    width = sig * pass_sigma / np.sqrt(sig ** 2 + pass_sigma ** 2)
    return float(centre), float(width * FWHM / centre)


def received(model: SensorModel, fc: float, bw: float, kind: str) -> tuple[float, float]:
    """The pulse (centre MHz, bw) the ADC sees for a pulse of fc MHz, bw: an OA pulse through
    the transducer's one-way receive band (the same ring transducer, paper SIII-1; the two-way
    chain us_fc/us_bw is its square, so one way is sqrt(2) wider), then every arrival through
    the anti-alias low-pass. Without them a 1.6 MHz OA pulse aliases at 3.3 MS/s and its
    arrival moves by ~80 ns with the sampling phase."""
    if kind == "oa":
        fc, bw = through(fc, bw, model.us_fc_mhz, np.sqrt(2) * model.us_bw * model.us_fc_mhz
                         / FWHM)
    return through(fc, bw, 0.0, model.aa_cutoff_mhz / np.sqrt(np.log(2)))


def _sigma_us(fc: float, bw: float) -> float:
    """Envelope std (us) of a Gaussian pulse of fc MHz and -6 dB fractional bandwidth bw."""
    return np.sqrt(2 * np.log(2)) / (np.pi * bw * fc)


def _pulse(t_us: np.ndarray, fc: float, bw: float) -> np.ndarray:
    """Gaussian-modulated cosine, unit peak: the transducer's band-limited arrival."""
    sigma = _sigma_us(fc, bw)
    return np.exp(-0.5 * (t_us / sigma) ** 2) * np.cos(2 * np.pi * fc * t_us)


PULSE_SPAN = 9.0  # sigmas: beyond this the envelope is below exp(-40), 4e-18 of the peak


def _add_pulse(x: np.ndarray, t_us: np.ndarray, t0_us: float, amp: float, fc: float,
               bw: float) -> slice:
    """x += amp * _pulse(t_us - t0_us, fc, bw), computed only where the envelope is not
    negligible (t_us uniformly spaced, increasing): the same sum at a fraction of the cost
    for a 1024-sample shot, which the emulator draws a thousand times a second. Returns the
    samples it changed."""
    sigma = _sigma_us(fc, bw)
    dt = (t_us[-1] - t_us[0]) / (len(t_us) - 1) if len(t_us) > 1 else 1.0
    lo = max(int(np.floor((t0_us - PULSE_SPAN * sigma - t_us[0]) / dt)), 0)
    hi = min(int(np.ceil((t0_us + PULSE_SPAN * sigma - t_us[0]) / dt)) + 1, len(t_us))
    if hi > lo:
        x[lo:hi] += amp * _pulse(t_us[lo:hi] - t0_us, fc, bw)
    return slice(lo, max(hi, lo))


def roughness(hit: Hit, scale_mm: float, kind: str, seed: int) -> float:
    """Range scatter of the surface under the spot: fixed per surface point (0.2 mm cells), so
    averaging shots does not remove it; Laplace for OA, Gaussian for US (mm)."""
    if hit.local is None or scale_mm == 0:
        return 0.0
    key = np.round(np.asarray(hit.local) / 0.2).astype(int).tobytes() + \
        f"{hit.obj}:{kind}:{seed}".encode()
    return keyed_laplace(key, scale_mm) if kind == "oa" else keyed_normal(key, scale_mm)


def arrival_times_us(d_mm: float, model: SensorModel) -> tuple[float, float]:
    """(OA, US) arrival times after the trigger for a target at d mm (no scatter)."""
    c = model.c_mm_us
    return model.t0_oa_us + d_mm / c, model.t0_us_us + 2 * d_mm / c


def synthesize(hit: Hit, model: SensorModel, t_us: np.ndarray, rng: np.random.Generator,
               seed: int = 0) -> np.ndarray:
    """Analog waveform (counts about 0) at sample times t_us after the laser edge."""
    x = np.zeros(t_us.shape)
    w = _add_pulse(x, t_us, model.t0_us_us, model.bang_amp,
                   *received(model, model.us_fc_mhz, model.us_bw, "us"))
    x[w] *= np.exp(-np.clip(t_us[w] - model.t0_us_us, 0, None) / model.bang_decay_us)
    for ret in (hit, *hit.later):
        _add_return(x, ret, model, t_us, rng, seed)
    x += rng.normal(0, model.noise_counts, t_us.shape)
    if rng.random() < model.spike_prob:
        x[rng.integers(0, len(x))] += model.spike_amp * rng.choice([-1, 1])
    return x


def _add_return(x: np.ndarray, hit: Hit, model: SensorModel, t_us: np.ndarray,
                rng: np.random.Generator, seed: int) -> None:
    """Add one return's OA pulse and US echo to x (counts)."""
    mat = model.materials.get(hit.material) if hit.material else None
    if mat is None or hit.overlap <= 0:
        return
    if hit.path:
        _add_interface(x, hit, mat, model, t_us, rng)
        return
    spread = 1.0 / (1.0 + hit.d / model.spread_mm) * (1 + 10 / model.spread_mm)
    var = mat.variability
    c = model.c_mm_us
    if mat.oa:
        d = hit.d + roughness(hit, mat.roughness_oa_mm, "oa", seed)
        amp = mat.oa_amp * hit.overlap * spread * np.sqrt(hit.cos_incidence)
        amp *= rng.lognormal(0, var)
        fc = mat.oa_fc_mhz * (1 + rng.normal(0, var / 3))
        _add_pulse(x, t_us, model.t0_oa_us + d / c, amp, *received(model, fc, mat.oa_bw, "oa"))
    if mat.us:
        d = hit.d + roughness(hit, mat.roughness_us_mm, "us", seed)
        angle = np.degrees(np.arccos(np.clip(hit.cos_incidence, 0, 1)))
        amp = mat.us_amp * hit.overlap * spread ** 2
        amp *= np.exp(-(angle / model.us_angle_deg) ** 2)
        amp *= rng.lognormal(0, var)
        fc = model.us_fc_mhz * mat.us_fc_scale * (1 + rng.normal(0, var / 3))
        t_echo = model.t0_us_us + 2 * d / c
        if not mat.ring_gain:
            _add_pulse(x, t_us, t_echo, amp, *received(model, fc, model.us_bw, "us"))
            return
        tau = t_us - t_echo
        echo = _pulse(tau, *received(model, fc, model.us_bw, "us"))
        ring = np.where(tau > 0, np.exp(-tau / mat.ring_decay_us), 0.0)
        echo += mat.ring_gain * (1 + rng.normal(0, var)) * ring * np.sin(
            2 * np.pi * mat.ring_fc_mhz * tau)
        x += amp * echo


def _add_interface(x: np.ndarray, hit: Hit, mat: Material, model: SensorModel,
                   t_us: np.ndarray, rng: np.random.Generator) -> None:
    """Add the US echo of a surface inside an object (x in counts): it arrives later by the
    time the sound spent crossing each medium on the way (at that medium's speed, not the
    air's) and weaker by each medium's `us_through`. No OA: the laser is absorbed at the
    first surface (or passes a transparent one and is not modelled further)."""
    if not mat.us:
        return
    c = model.c_mm_us
    delay, gain = 0.0, 1.0
    for name, mm in hit.path:
        medium = model.materials.get(name)
        if medium is None or medium.c_mm_us <= 0:
            return  # sound does not cross it (porous, unknown)
        delay += 2 * mm * (1 / medium.c_mm_us - 1 / c)
        gain *= medium.us_through
    spread = 1.0 / (1.0 + hit.d / model.spread_mm) * (1 + 10 / model.spread_mm)
    angle = np.degrees(np.arccos(np.clip(hit.cos_incidence, 0, 1)))
    amp = mat.us_amp * gain * hit.overlap * spread ** 2
    amp *= np.exp(-(angle / model.us_angle_deg) ** 2) * rng.lognormal(0, mat.variability)
    fc = model.us_fc_mhz * mat.us_fc_scale * (1 + rng.normal(0, mat.variability / 3))
    _add_pulse(x, t_us, model.t0_us_us + 2 * hit.d / c + delay, amp,
               *received(model, fc, model.us_bw, "us"))


def interface_time_us(d_mm: float, path: tuple[tuple[str, float], ...],
                      model: SensorModel) -> float:
    """Arrival (us after the trigger) of the US echo of a surface d mm along the beam reached
    through `path` ((material, mm) legs inside the object), as `synthesize` places it."""
    c = model.c_mm_us
    return model.t0_us_us + 2 * d_mm / c + sum(
        2 * mm * (1 / model.materials[m].c_mm_us - 1 / c) for m, mm in path)


def to_adc(x: np.ndarray, model: SensorModel) -> np.ndarray:
    """16-bit ADC: offset to mid-scale, quantise, clip."""
    return np.clip(np.rint(x + model.baseline), 0, 65535).astype(np.uint16)
