"""Pulse-echo physics of the simulated bench: bone motion in, 8-bit segmented records out.

Pure, vectorised functions on numpy arrays (no I/O, no state). The measurement principle is
that of thesis ch. 8.2-8.3: a 5 MHz single-element transducer sends a short pulse toward a
bony landmark under the skin; the echo's time of flight changes with the bone's displacement
along the beam, t = 2 (d - u) / c, u positive toward the transducer.

What a record contains (one segment per pulse, ``n_samples`` samples at ``sample_rate_hz``,
first sample ``delay_s + trigger_offset_s[s]`` after that segment's trigger, the time
convention of :class:`pelvislab.drivers.interfaces.SegmentedRecord`):

- the **specular bone echo**: a Gaussian-modulated cosine, centre 5 MHz, -6 dB fractional
  bandwidth 50 % by default, reflection coefficient of a soft-tissue/cortical-bone interface
  (Z about 1.6 and 7.8 MRayl, R = 0.66), delayed by the round trip to the bone;
- **frequency-dependent attenuation** of soft tissue, alpha = 0.5 dB/(cm MHz) over the round
  trip, which lowers the echo and shifts its spectrum down;
- **speckle**: weak random point scatterers in the tissue above the bone (none behind it: bone
  shadows), moving with the fraction z/d of the bone displacement (the tissue column between
  the fixed transducer face and the bone is compressed uniformly);
- optional **static clutter**: echoes that do not move at all (reverberation in a stand-off);
- white Gaussian receiver **noise** at a set SNR (bone-echo peak over noise RMS), then the
  receiver gain, the digitizer's 8-bit **quantisation and clipping**.

Every moving part is a *layer*: a waveform known at rest whose arrival is shifted per segment
by a small delay. Each layer is synthesised once, in the frequency domain, on the few FFT bins
where the pulse has energy; per-segment shifts become phase ramps, and a single inverse real
FFT over all segments gives every record at once. Sub-sample delays are therefore exact (no
interpolation error): the band-limited pulse is sampled far above Nyquist (500 MS/s vs
< 15 MHz of content).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.fft

__all__ = [
    "BONE_REFLECTION",
    "TISSUE_ATTENUATION_DB_PER_M_MHZ",
    "Acoustics",
    "Receiver",
    "attenuation_gain",
    "bone_amplitude_v",
    "bone_echo_peak_v",
    "layer_spectrum",
    "padded_length",
    "pulse_sigma_s",
    "pulse_spectrum",
    "quantize",
    "receiver_response",
    "speckle_scatterers",
    "synthesize_channel",
    "synthesize_layers",
    "white_noise",
]

# Soft tissue (Z ~ 1.6 MRayl) on cortical bone (Z ~ 7.8 MRayl): R = (7.8-1.6)/(7.8+1.6).
BONE_REFLECTION = 0.66
# Average soft-tissue attenuation, 0.5 dB/(cm MHz) = 50 dB/(m MHz).
TISSUE_ATTENUATION_DB_PER_M_MHZ = 50.0
# Gaussian pulse: -6 dB (half amplitude) points of the spectrum at f0 +- B/2.
_HALF_AMPLITUDE_FACTOR = math.sqrt(2.0 * math.log(2.0)) / (2.0 * math.pi)
# Layers are synthesised over +-_PULSE_SIGMAS standard deviations of the envelope.
_PULSE_SIGMAS = 4.0


def pulse_sigma_s(center_frequency_hz: float, fractional_bandwidth: float) -> float:
    """Envelope standard deviation (s) of a Gaussian pulse with the given -6 dB bandwidth.

    The pulse is p(t) = exp(-t^2 / (2 sigma^2)) cos(2 pi f0 t); its amplitude spectrum falls
    to one half at f0 +- B/2 with B = fractional_bandwidth * f0, i.e.
    sigma = sqrt(2 ln 2) / (pi B).
    """
    if center_frequency_hz <= 0 or fractional_bandwidth <= 0:
        raise ValueError("centre frequency and fractional bandwidth must be > 0")
    bandwidth_hz = fractional_bandwidth * center_frequency_hz
    return 2.0 * _HALF_AMPLITUDE_FACTOR / bandwidth_hz


def pulse_spectrum(frequency_hz: np.ndarray, center_frequency_hz: float,
                   fractional_bandwidth: float) -> np.ndarray:
    """Continuous Fourier transform (V s per V of peak) of the unit-peak pulse at t = 0.

    p(t) = exp(-t^2/(2 sigma^2)) cos(2 pi f0 t) has
    P(f) = sigma sqrt(2 pi)/2 [exp(-2 pi^2 sigma^2 (f-f0)^2) + exp(-2 pi^2 sigma^2 (f+f0)^2)].
    """
    f = np.asarray(frequency_hz, dtype=np.float64)
    sigma = pulse_sigma_s(center_frequency_hz, fractional_bandwidth)
    k = 2.0 * math.pi**2 * sigma**2
    scale = sigma * math.sqrt(2.0 * math.pi) / 2.0
    return scale * (np.exp(-k * (f - center_frequency_hz) ** 2)
                    + np.exp(-k * (f + center_frequency_hz) ** 2))


def attenuation_gain(frequency_hz: np.ndarray, path_m: float,
                     alpha_db_per_m_mhz: float = TISSUE_ATTENUATION_DB_PER_M_MHZ) -> np.ndarray:
    """Amplitude factor of soft tissue over an acoustic path (m), linear in frequency.

    alpha(f) = alpha_db_per_m_mhz * f[MHz] dB/m; gain = 10^(-alpha(f) path / 20). For the
    round trip to a bone at depth d, path = 2 d.
    """
    f_mhz = np.abs(np.asarray(frequency_hz, dtype=np.float64)) * 1e-6
    return 10.0 ** (-alpha_db_per_m_mhz * f_mhz * path_m / 20.0)


def _butterworth_lowpass(s_norm: np.ndarray, order: int) -> np.ndarray:
    """Analog Butterworth low-pass H(s) at normalised complex frequency s/omega_c."""
    k = np.arange(1, order + 1)
    poles = np.exp(1j * np.pi * (2 * k + order - 1) / (2 * order))
    h = np.ones(s_norm.shape, dtype=np.complex128)
    for p in poles:
        h = h * (-p / (s_norm - p))
    return h


def receiver_response(frequency_hz: np.ndarray, high_pass_hz: float | None,
                      low_pass_hz: float | None, order: int = 2) -> np.ndarray:
    """Complex response of the receiver's analog filters (Butterworth, ``order`` poles each).

    ``None`` means that filter is out (full band). Low-pass H(s/w_c); high-pass H(w_c/s).
    """
    f = np.asarray(frequency_hz, dtype=np.float64)
    response = np.ones(f.shape, dtype=np.complex128)
    if low_pass_hz is not None:
        response = response * _butterworth_lowpass(1j * f / low_pass_hz, order)
    if high_pass_hz is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            s_inv = np.where(f > 0, high_pass_hz / np.where(f > 0, 1j * f, 1.0), np.inf)
        hp = np.where(f > 0, _butterworth_lowpass(s_inv, order), 0.0)
        response = response * hp
    return response


def padded_length(n_samples: int, sample_rate_hz: float, sigma_s: float) -> int:
    """FFT length (samples) so that layers cannot wrap around into the kept record.

    Scatterers are placed up to 4 sigma outside the record and their pulses reach 4 sigma
    further, so the period must exceed the record by 8 sigma.
    """
    guard = int(math.ceil(2.0 * _PULSE_SIGMAS * sigma_s * sample_rate_hz))
    return int(scipy.fft.next_fast_len(n_samples + guard + 8, real=True))


def layer_spectrum(frequency_hz: np.ndarray, arrival_s: np.ndarray, amplitude: np.ndarray,
                   pulse: np.ndarray) -> np.ndarray:
    """Spectrum of a set of echoes: sum_j a_j P(f) exp(-2 pi i f t_j).

    ``arrival_s`` are pulse centres (s) on the record's time axis (0 = first sample),
    ``amplitude`` their peak amplitudes (V), ``pulse`` = P(f) times every per-channel filter.
    Returns the continuous transform (V s), shape of ``frequency_hz``.
    """
    t = np.asarray(arrival_s, dtype=np.float64)
    a = np.asarray(amplitude, dtype=np.float64)
    if t.size == 0:
        return np.zeros(np.shape(frequency_hz), dtype=np.complex128)
    phase = np.exp(-2j * math.pi * np.outer(frequency_hz, t))
    return pulse * (phase @ a)


def synthesize_layers(spectra: np.ndarray, shifts_s: np.ndarray, frequency_hz: np.ndarray,
                      n_fft: int, n_samples: int, sample_rate_hz: float,
                      dtype: type = np.float64) -> np.ndarray:
    """Records (V, ``dtype`` float64 or float32, (n_segments, n_samples)) of shifted layers.

    ``spectra`` (n_layers, n_bins) are continuous transforms on the FFT bins ``frequency_hz``
    (the lowest n_bins bins of an ``n_fft``-point real FFT; higher bins are zero: the pulse
    has no energy there). ``shifts_s`` (n_layers, n_segments): extra delay of each layer in
    each segment (positive = later). Record s is
    irfft(sum_l S_l(f) exp(-2 pi i f shift_ls)) * fs, first ``n_samples`` samples.
    """
    spectra = np.atleast_2d(spectra)
    shifts_s = np.atleast_2d(shifts_s)
    n_bins = spectra.shape[1]
    n_segments = shifts_s.shape[1]
    complex_type = np.complex64 if dtype == np.float32 else np.complex128
    full = np.zeros((n_segments, n_fft // 2 + 1), dtype=complex_type)
    f = np.asarray(frequency_hz, dtype=np.float64)
    df = sample_rate_hz / n_fft
    if not np.allclose(f, df * np.arange(n_bins), rtol=0, atol=1e-9 * df):
        raise ValueError("frequency_hz must be the lowest bins of the n_fft-point real FFT")
    acc = full[:, :n_bins]
    for layer, shift in zip(spectra, shifts_s, strict=True):
        # The phase ramp exp(-2 pi i f_k shift) = z^k with z = exp(-2 pi i df shift): a
        # cumulative product is 5x cheaper than complex exponentials (rounding ~k eps).
        ramp = np.empty((n_segments, n_bins), dtype=np.complex128)
        ramp[:, 0] = 1.0
        if n_bins > 1:
            ramp[:, 1:] = np.exp(-2j * math.pi * df * np.asarray(shift))[:, None]
            np.cumprod(ramp, axis=1, out=ramp)
        # DFT of samples ~= fs * continuous transform (band-limited, time-limited layers)
        acc += (layer * sample_rate_hz)[None, :] * ramp
    records = scipy.fft.irfft(full, n=n_fft, axis=1)
    return records[:, :n_samples]


def quantize(volts: np.ndarray, full_scale_v: float, offset_v: float = 0.0,
             n_bits: int = 8) -> tuple[np.ndarray, float]:
    """8-bit ADC: codes and volts per count (Acqiris convention v = code * vpc - offset).

    ``full_scale_v`` spans the 2^n_bits codes; codes outside [-2^(n-1), 2^(n-1)-1] clip.
    Returns (int8 codes, volts_per_count).
    """
    if full_scale_v <= 0:
        raise ValueError(f"full_scale_v must be > 0, got {full_scale_v}")
    levels = 2**n_bits
    volts_per_count = full_scale_v / levels
    codes = np.rint((np.asarray(volts) + offset_v) / volts_per_count)
    np.clip(codes, -(levels // 2), levels // 2 - 1, out=codes)
    return codes.astype(np.int8 if n_bits <= 8 else np.int16), volts_per_count


def speckle_scatterers(rng: np.random.Generator, depth_from_m: float, depth_to_m: float,
                       density_per_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Random point scatterers (depths m, unit-variance Gaussian amplitudes) in a depth range.

    Poisson number of scatterers, uniform in depth: fully developed speckle along the beam.
    """
    length = max(depth_to_m - depth_from_m, 0.0)
    n = int(rng.poisson(density_per_m * length))
    depth = rng.uniform(depth_from_m, depth_to_m, n)
    return depth, rng.standard_normal(n)


@dataclass(frozen=True)
class Acoustics:
    """The acoustic path of one channel: transducer, tissue and bone.

    Amplitudes are volts at the receiver input at 0 dB gain and 100 V pulse voltage.
    """

    bone_depth_m: float = 8.2e-3
    """Skin (transducer face) to bone surface, m (a lean subject). At 1540 m/s the echo
    returns 10.65 us after the pulse: sample 325 of a record starting at 10 us."""
    speed_of_sound_m_s: float = 1540.0
    """True speed of sound in the tissue, m/s (the tracker assumes the bench's value)."""
    center_frequency_hz: float = 5e6
    fractional_bandwidth: float = 0.5
    """-6 dB fractional bandwidth of the pulse."""
    attenuation_db_per_m_mhz: float = TISSUE_ATTENUATION_DB_PER_M_MHZ
    transmit_v: float = 0.0075
    """Echo of a perfect reflector at zero depth, V at 0 dB gain and 100 V pulses (sets the
    overall level: the default bone echo peaks at ~0.3 V after 40 dB gain, 60 % of the
    +-0.5 V range of a 1 V full scale)."""
    bone_reflection: float = BONE_REFLECTION
    speckle_level_db: float = -30.0
    """RMS amplitude of one speckle scatterer relative to the bone echo (before attenuation)."""
    speckle_density_per_m: float = 20e3
    """Scatterers per metre of depth (20 per mm: several per resolution cell)."""


@dataclass(frozen=True)
class Receiver:
    """Receiver and noise settings of one channel (pulser/receiver + digitizer input)."""

    gain_db: float = 40.0
    pulse_voltage_v: float = 100.0
    """Pulser voltage, V (5077PR: 100-400 V); echo amplitudes scale with it."""
    high_pass_hz: float | None = None
    low_pass_hz: float | None = None
    snr_db: float = 30.0
    """Bone-echo peak envelope (after attenuation and filters) over the noise RMS, dB;
    ``inf`` for no noise (quantisation remains)."""
    enabled: bool = True
    """False: the pulser does not fire (no echoes, noise only)."""


def bone_echo_peak_v(acoustics: Acoustics, receiver: Receiver, sample_rate_hz: float) -> float:
    """Peak envelope (V, after gain) of the bone echo as it appears in the record.

    The envelope is the modulus of the analytic signal; this is the amplitude the SNR refers
    to (same convention as the tracking tests: peak envelope over noise standard deviation).
    """
    sigma = pulse_sigma_s(acoustics.center_frequency_hz, acoustics.fractional_bandwidth)
    n_fft = padded_length(64, sample_rate_hz, sigma)
    f = scipy.fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    shape = _channel_filter(f, acoustics, receiver)
    t0 = n_fft / 2.0 / sample_rate_hz
    one_sided = shape * np.exp(-2j * math.pi * f * t0) * sample_rate_hz
    # analytic signal: positive frequencies doubled, negative ones zero
    full = np.zeros(n_fft, dtype=np.complex128)
    full[: f.size] = one_sided
    full[1: f.size] *= 2.0
    envelope = np.abs(scipy.fft.ifft(full))
    amplitude = bone_amplitude_v(acoustics, receiver)
    return float(np.max(envelope) * amplitude * 10.0 ** (receiver.gain_db / 20.0))


def bone_amplitude_v(acoustics: Acoustics, receiver: Receiver) -> float:
    """Peak of the bone echo before attenuation, filters and gain, V."""
    return acoustics.transmit_v * acoustics.bone_reflection * receiver.pulse_voltage_v / 100.0


def _channel_filter(f: np.ndarray, acoustics: Acoustics, receiver: Receiver) -> np.ndarray:
    """Pulse x round-trip attenuation x receiver filters, on frequencies f (Hz)."""
    return (pulse_spectrum(f, acoustics.center_frequency_hz, acoustics.fractional_bandwidth)
            * attenuation_gain(f, 2.0 * acoustics.bone_depth_m,
                               acoustics.attenuation_db_per_m_mhz)
            * receiver_response(f, receiver.high_pass_hz, receiver.low_pass_hz))


def synthesize_channel(
    acoustics: Acoustics,
    receiver: Receiver,
    displacement_m: np.ndarray,
    trigger_offset_s: np.ndarray,
    *,
    sample_rate_hz: float,
    n_samples: int,
    delay_s: float,
    full_scale_v: float,
    offset_v: float = 0.0,
    rng: np.random.Generator,
    depth_offset_m: float = 0.0,
    speckle_seed: int = 0,
    clutter: tuple[np.ndarray, np.ndarray] | None = None,
    jitter_s: float = 0.0,
) -> tuple[np.ndarray, float]:
    """8-bit records of one channel for one sequence acquisition.

    ``displacement_m`` (n_segments,): bone displacement along the beam at each pulse, m,
    positive toward the transducer. ``depth_offset_m``: a slow change of the bone depth
    common to the record (e.g. subject drift; positive = deeper), m. ``trigger_offset_s``
    (n_segments,): sub-sample trigger offset of each segment (``SegmentedRecord``
    convention: sample k of segment s is at delay_s + k/fs + trigger_offset_s[s]).
    ``clutter``: (arrival times s after the trigger, peak amplitudes V) of static echoes.
    ``speckle_seed`` fixes the tissue (same seed, same speckle pattern: the tissue does not
    change between steps); ``rng`` draws the noise and jitter. ``jitter_s``: RMS of a
    trigger timing error that is *not* in ``trigger_offset_s``.

    Returns (int8 codes (n_segments, n_samples), volts_per_count).
    """
    u = np.asarray(displacement_m, dtype=np.float64)
    offsets = np.asarray(trigger_offset_s, dtype=np.float64)
    n_segments = u.shape[0]
    c = acoustics.speed_of_sound_m_s
    sigma = pulse_sigma_s(acoustics.center_frequency_hz, acoustics.fractional_bandwidth)
    n_fft = padded_length(n_samples, sample_rate_hz, sigma)
    f_all = scipy.fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    shape_all = _channel_filter(f_all, acoustics, receiver)
    # keep the bins that carry the pulse (everything above is < 1e-9 of the peak)
    band = np.abs(shape_all) > 1e-9 * np.max(np.abs(shape_all))
    n_bins = int(np.nonzero(band)[0][-1]) + 1
    f = f_all[:n_bins]
    shape = shape_all[:n_bins]

    # record time axis: 0 = first sample of a segment whose trigger offset is 0
    depth = acoustics.bone_depth_m + depth_offset_m
    bone_t = 2.0 * depth / c - delay_s
    gain = 10.0 ** (receiver.gain_db / 20.0)
    amp = bone_amplitude_v(acoustics, receiver) if receiver.enabled else 0.0

    margin_s = _PULSE_SIGMAS * sigma
    window_lo = -margin_s
    window_hi = n_samples / sample_rate_hz + margin_s
    spectra = [layer_spectrum(f, [bone_t], [amp], shape)]
    jitter = rng.standard_normal(n_segments) * jitter_s if jitter_s > 0 else 0.0
    common = jitter - offsets
    shifts = [-2.0 * u / c + common]

    # speckle in the tissue above the bone that falls inside the (padded) record
    depth_lo = max((window_lo + delay_s) * c / 2.0, 0.0)
    depth_hi = min((window_hi + delay_s) * c / 2.0, depth)
    if amp > 0 and depth_hi > depth_lo and acoustics.speckle_density_per_m > 0:
        tissue = np.random.default_rng(speckle_seed)
        # draw the whole column down to the bone so the pattern does not depend on the gate
        z, a = speckle_scatterers(tissue, 0.0, depth, acoustics.speckle_density_per_m)
        keep = (z >= depth_lo) & (z <= depth_hi)
        z, a = z[keep], a[keep]
        if z.size:
            level = amp * 10.0 ** (acoustics.speckle_level_db / 20.0)
            spectra.append(layer_spectrum(f, 2.0 * z / c - delay_s, level * a, shape))
            # one motion fraction for the layer: the scatterers in a record lie within
            # ~1 mm of the bone, so z/d varies by a few per cent across it
            fraction = float(np.mean(z) / depth)
            shifts.append(-2.0 * u * fraction / c + common)
    if clutter is not None and len(clutter[0]):
        arrival, level = clutter
        spectra.append(layer_spectrum(f, np.asarray(arrival) - delay_s, level, shape))
        shifts.append(np.zeros(n_segments) + common)

    if full_scale_v <= 0:
        raise ValueError(f"full_scale_v must be > 0, got {full_scale_v}")
    volts_per_count = full_scale_v / 256.0
    # gain and volts -> codes folded into the (small) spectra: one pass less over the record
    counts = synthesize_layers(np.array(spectra) * (gain / volts_per_count), np.array(shifts),
                               f, n_fft, n_samples, sample_rate_hz, dtype=np.float32)
    noise_rms = 0.0
    if receiver.snr_db is not None and math.isfinite(receiver.snr_db):
        reference = bone_echo_peak_v(acoustics, replace(receiver, enabled=True), sample_rate_hz)
        noise_rms = reference / 10.0 ** (receiver.snr_db / 20.0)
    return _digitize(counts, noise_rms / volts_per_count, offset_v / volts_per_count,
                     rng), volts_per_count


_NOISE_BANK_SIZE = 1 << 22


@functools.lru_cache(maxsize=2)
def _noise_bank(seed: int) -> np.ndarray:
    """A fixed block of standard normal float32 samples (16 MB), drawn once per seed."""
    return np.random.default_rng(seed).standard_normal(_NOISE_BANK_SIZE, dtype=np.float32)


def white_noise(rng: np.random.Generator, shape: tuple[int, ...], rms: float) -> np.ndarray:
    """White Gaussian noise (float32) of the given RMS, fast enough for 1e6 samples per record.

    Drawing 1e6 normal samples costs ~10 ms, a fifth of the step budget, so large records
    take a contiguous slice at a random offset (and random sign) of a fixed bank of 4 Mi
    samples: exactly Gaussian and white within a record; two records share values only at
    random, unaligned positions. Small records draw fresh samples.
    """
    n = int(np.prod(shape))
    if n > _NOISE_BANK_SIZE // 2 or n < 65536:
        return (rng.standard_normal(n, dtype=np.float32) * np.float32(rms)).reshape(shape)
    bank = _noise_bank(0x5EED)
    start = int(rng.integers(0, _NOISE_BANK_SIZE - n))
    sign = np.float32(rms if rng.random() < 0.5 else -rms)
    return (bank[start:start + n] * sign).reshape(shape)


def _digitize(counts: np.ndarray, noise_rms_counts: float, offset_counts: float,
              rng: np.random.Generator) -> np.ndarray:
    """White noise, offset and 8-bit quantisation/clipping of a record in ADC counts."""
    if noise_rms_counts > 0:
        scaled = counts + white_noise(rng, counts.shape, noise_rms_counts)
    else:
        scaled = np.array(counts, dtype=np.float32)
    if offset_counts:
        scaled += np.float32(offset_counts)
    np.rint(scaled, out=scaled)
    np.clip(scaled, -128, 127, out=scaled)
    return scaled.astype(np.int8)
