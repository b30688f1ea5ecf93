"""Counter-based random numbers shared by every workflow.

Every number is a pure function of (seed, stream, index), so results do not depend on threads,
chunking or the order of evaluation. The generator is SplitMix64 read at a position (state = key
+ counter * gamma, output = Stafford's mix13 finaliser). Normals come from Marsaglia and Tsang's
ziggurat (1024 layers) with independent bits for the value (32) and the layer (10); each
layer's scale and (rounded-down) threshold share one table word (`ziggurat_tables`); the slow
path (about 0.4 % of draws) draws from a separate stream. The kinematics reads one sequence per
seed for the error amplitudes at 32 * trial + k and, for the noise of trial t, positions 4 *
point + slot of a sequence keyed by a double hash of (seed, t) (`trial_key`): consecutive
positions, the way SplitMix64 is meant to be used (a strided counter, e.g. trial << 32, gives
visibly correlated outputs). The sweep keys one sequence per node (`trial_key` of the node
index) and reads positions 4 * trial, 4 * trial + 1 for the three normals of a trial.
Plain-numpy twins: `cfm_fem.testing`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from .options import JIT, PJIT

GAMMA = np.uint64(0x9E3779B97F4A7C15)


_BELOW_ONE = 1.0 - 2.0**-53  # the largest double below 1


#: Ziggurat layers, base-strip edge r and layer area v (Marsaglia & Tsang's construction; r and
#: v solved so that the layers close at x = 0, which gives their published 256-layer values).
ZIG_LAYERS = 1024


_ZIG_R = 4.038849846109504


_ZIG_V = 0.0012263246463530893


_ZIG_MASK = np.uint64(ZIG_LAYERS - 1)


_M1 = np.uint64(0xBF58476D1CE4E5B9)


_M2 = np.uint64(0x94D049BB133111EB)


_LOW32 = np.uint64(0xFFFFFFFF)


#: Stream identifiers mixed into the seed: error amplitudes, per-point noise, ziggurat fallback.
STREAM_ERRORS = np.uint64(0x45525253)


STREAM_NOISE = np.uint64(0x4E4F4953)


STREAM_FALLBACK = np.uint64(0x46414C4C)


STREAM_SWEEP = np.uint64(0x53574550)


def ziggurat_tables(layers: int = ZIG_LAYERS, packed: bool = True):
    """Ziggurat tables of Marsaglia & Tsang (2000) for 32-bit signed values.

    With 1024 layers about 0.43 % of draws take the slow path (1.3 % of the kinematics' triples
    of normals), against 1.5 % with the classic 256 layers (r = 3.6541528853610088,
    v = 4.92867323399e-3) and 2.7 % with 128; the top layer is always slow. The slow path
    (an exp, a branch that cannot be predicted) cost the kinematics ~3 ns per sample at 256
    layers; the tables (8 KB each) stay in L1.

    ``packed`` (the generator's tables): each layer's threshold and scale share one 64-bit
    word, so the vectorised fast path reads one table entry per normal instead of two (one
    gather less per normal: 0.25 ns of ~1 ns). The threshold is rounded down to a multiple of
    2**ZIG_THRESHOLD_SHIFT and stored in the low ZIG_THRESHOLD_BITS mantissa bits of the
    scale; a value between the rounded and the exact threshold takes the slow path, whose
    wedge test accepts it (the density is above the wedge there), so the rounding moves no
    probability; the scale moves by less than 2**-36 of itself (1.5e-11). `packed_layers`
    gives the words.

    Returns
    -------
    kn : ndarray, shape (layers,), float64
        Acceptance thresholds on |value| (value in [-2**31, 2**31)).
    wn : ndarray, shape (layers,), float64
        Scale of each layer: x = value * wn[layer].
    fn : ndarray, shape (layers,), float64
        exp(-x**2 / 2) at the layer edges.
    """
    r, v = {
        128: (3.442619855899, 9.91256303526217e-3),
        256: (3.6541528853610088, 4.92867323399e-3),
        1024: (_ZIG_R, _ZIG_V),
    }[layers]
    m1 = 2.0**31
    dn = r
    tn = dn
    kn = np.zeros(layers)
    wn = np.zeros(layers)
    fn = np.zeros(layers)
    q = v / math.exp(-0.5 * dn * dn)
    kn[0] = (dn / q) * m1
    kn[1] = 0.0
    wn[0] = q / m1
    wn[layers - 1] = dn / m1
    fn[0] = 1.0
    fn[layers - 1] = math.exp(-0.5 * dn * dn)
    for i in range(layers - 2, 0, -1):
        dn = math.sqrt(-2.0 * math.log(v / dn + math.exp(-0.5 * dn * dn)))
        kn[i + 1] = (dn / tn) * m1
        tn = dn
        fn[i] = math.exp(-0.5 * dn * dn)
        wn[i] = dn / m1
    if packed:
        word = packed_layers(kn, wn)
        kn = (word & _THRESHOLD_MASK).astype(np.float64) * 2.0**ZIG_THRESHOLD_SHIFT
        wn = word.view(np.float64)
    return kn, wn, fn


#: Packed ziggurat layers: thresholds in units of 2**ZIG_THRESHOLD_SHIFT (< 2**31 in all), in
#: the low ZIG_THRESHOLD_BITS bits of the scale's mantissa.
ZIG_THRESHOLD_SHIFT = 15


ZIG_THRESHOLD_BITS = 16


_THRESHOLD_MASK = np.uint64(2**ZIG_THRESHOLD_BITS - 1)


def packed_layers(kn, wn):
    """One uint64 per layer: the bits of wn with the low ZIG_THRESHOLD_BITS mantissa bits
    replaced by floor(kn / 2**ZIG_THRESHOLD_SHIFT) (exact tables in, shape (layers,))."""
    units = np.floor(np.asarray(kn) / 2.0**ZIG_THRESHOLD_SHIFT).astype(np.uint64)
    if np.any(units > _THRESHOLD_MASK):
        raise ValueError("ziggurat threshold does not fit its bits")
    bits = np.asarray(wn, dtype=np.float64).view(np.uint64)
    return (bits & ~_THRESHOLD_MASK) | units


#: Trailing-zero count of a power of two by de Bruijn multiplication (scans of flag words).
_DEBRUIJN = np.uint64(0x03F79D71B4CB0A89)


_DEBRUIJN_INDEX = np.zeros(64, dtype=np.int64)


for _b in range(64):
    _DEBRUIJN_INDEX[((1 << _b) * 0x03F79D71B4CB0A89 & (2**64 - 1)) >> 58] = _b


del _b


# Module constants: numba freezes global arrays into the compiled code, so the hot loops pass
# no array arguments for them (array arguments of helpers cost reference counting per call).
_KN, _WN, _FN = ziggurat_tables()


_ZIG_WORDS = packed_layers(*ziggurat_tables(packed=False)[:2])


_THRESHOLD_UNIT = 2.0**ZIG_THRESHOLD_SHIFT


@intrinsic
def _float_from_bits(typingctx, bits):
    """The float64 whose IEEE-754 bits are the uint64 ``bits`` (a cast that vectorises)."""
    if bits != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(types.uint64), codegen


@nb.njit(inline="always", **JIT)
def mix64(z):
    """SplitMix64 output function (Stafford mix13): a bijection of uint64."""
    z = np.uint64(z)  # a key boxed by Python may arrive as int64; int64 + uint64 is float64
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


@nb.njit(**JIT)
def stream_key(seed, stream):
    """Key of one random stream: a hash of (seed, stream id)."""
    return mix64(mix64(np.uint64(seed) * GAMMA + np.uint64(1)) ^ np.uint64(stream))


@nb.njit(inline="always", **JIT)
def _draw(key, counter):
    return mix64(np.uint64(key) + np.uint64(counter) * GAMMA)


@nb.njit(inline="always", **JIT)
def uniform53(h):
    """Uniform in (0, 1) from the top 53 bits: (k + 1/2) / 2**53, never 0 or 1 (k + 1/2 rounds
    to 2**53 for k = 2**53 - 1 alone, which takes the largest double below 1 instead)."""
    return min((np.float64(h >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0), _BELOW_ONE)


# Wichura's algorithm AS 241 (PPND16, Applied Statistics 37, 1988): rational approximations of
# degree 7 in three ranges of p, relative error about 1e-16.
_AS241_A = (3.3871328727963666080e0, 1.3314166789178437745e2, 1.9715909503065514427e3,
            1.3731693765509461125e4, 4.5921953931549871457e4, 6.7265770927008700853e4,
            3.3430575583588128105e4, 2.5090809287301226727e3)  # fmt: skip


_AS241_B = (1.0, 4.2313330701600911252e1, 6.8718700749205790830e2, 5.3941960214247511077e3,
            2.1213794301586595867e4, 3.9307895800092710610e4, 2.8729085735721942674e4,
            5.2264952788528545610e3)  # fmt: skip


_AS241_C = (1.42343711074968357734e0, 4.63033784615654529590e0, 5.76949722146069140550e0,
            3.64784832476320460504e0, 1.27045825245236838258e0, 2.41780725177450611770e-1,
            2.27238449892691845833e-2, 7.74545014278341407640e-4)  # fmt: skip


_AS241_D = (1.0, 2.05319162663775882187e0, 1.67638483018380384940e0, 6.89767334985100004550e-1,
            1.48103976427480074590e-1, 1.51986665636164571966e-2, 5.47593808499534494600e-4,
            1.05075007164441684324e-9)  # fmt: skip


_AS241_E = (6.65790464350110377720e0, 5.46378491116411436990e0, 1.78482653991729133580e0,
            2.96560571828504891230e-1, 2.65321895265761230930e-2, 1.24266094738807843860e-3,
            2.71155556874348757815e-5, 2.01033439929228813265e-7)  # fmt: skip


_AS241_F = (1.0, 5.99832206555887937690e-1, 1.36929880922735805310e-1, 1.48753612908506148525e-2,
            7.86869131145613259100e-4, 1.84631831751005468180e-5, 1.42151175831644588870e-7,
            2.04426310338993978564e-15)  # fmt: skip


@nb.njit(inline="always", **JIT)
def _poly7(c, x):
    """c[0] + c[1] x + ... + c[7] x**7 by Horner's rule."""
    y = c[7] * x + c[6]
    y = (y * x + c[5]) * x + c[4]
    y = (y * x + c[3]) * x + c[2]
    return (y * x + c[1]) * x + c[0]


@nb.njit(**JIT)
def ndtri(p):
    """Inverse of the standard normal CDF for p in (0, 1), full double precision.

    Wichura's AS 241 (PPND16): relative error about 1e-16, no special function calls in the
    central range (|p - 1/2| <= 0.425), one log and one square root in the tails; about 8 ns,
    a quarter of a rational guess refined by a Halley step on erfc.
    """
    q = p - 0.5
    if abs(q) <= 0.425:
        r = 0.180625 - q * q
        return q * _poly7(_AS241_A, r) / _poly7(_AS241_B, r)
    r = math.sqrt(-math.log(p if q < 0.0 else 1.0 - p))
    if r <= 5.0:
        r -= 1.6
        x = _poly7(_AS241_C, r) / _poly7(_AS241_D, r)
    else:
        r -= 5.0
        x = _poly7(_AS241_E, r) / _poly7(_AS241_F, r)
    return -x if q < 0.0 else x


@nb.njit(**JIT)
def pdf_ppf(code, par, u):
    """Inverse CDF of the kernel PDFs (codes in ``cfm_fem.models.mc.KERNEL_PDF_CODES``).

    Parameters
    ----------
    code : int
    par : ndarray, shape (4,)
    u : float in (0, 1)
    """
    p0 = par[0]
    p1 = par[1]
    p2 = par[2]
    if code == 0:
        return p0
    if code == 1:
        return p0 + (p1 - p0) * u
    if code == 2:
        return p0 + p1 * ndtri(u)
    if code == 3:
        fc = (p1 - p0) / (p2 - p0)
        if u < fc:
            return p0 + math.sqrt(u * (p2 - p0) * (p1 - p0))
        return p2 - math.sqrt((1.0 - u) * (p2 - p0) * (p2 - p1))
    if code == 4:
        s = math.sin(0.5 * math.pi * u)
        return p0 + (p1 - p0) * s * s
    # trapezoidal (code 5)
    ramp = 0.5 * (p1 - p0) * (1.0 - p2)
    h = 1.0 / (p1 - p0 - ramp)
    f1 = 0.5 * h * ramp
    if u < f1:
        return p0 + math.sqrt(2.0 * ramp * u / h)
    if u > 1.0 - f1:
        return p1 - math.sqrt(2.0 * ramp * (1.0 - u) / h)
    return p0 + ramp + (u - f1) / h


@nb.njit(**PJIT)
def draw_error_params(key, t0, n, codes, pars, out):
    """Error amplitudes of trials t0 .. t0+n-1 into ``out`` (n, k).

    Amplitude k of trial t uses uniform number (t * 32 + k) of the error stream ``key``.
    """
    k = codes.shape[0]
    for i in nb.prange(n):
        base = np.uint64(t0 + i) * np.uint64(32)
        for j in range(k):
            u = uniform53(_draw(key, base + np.uint64(j)))
            out[i, j] = pdf_ppf(codes[j], pars[j], u)


@nb.njit(**JIT)
def _zig_fallback(hz, iz, fkey):
    """Slow path of the ziggurat (Marsaglia & Tsang nfix); ``fkey`` keys a private stream."""
    kn, wn, fn = _KN, _WN, _FN
    c = np.uint64(0)
    while True:
        x = hz * wn[iz]
        if iz == 0:  # tail beyond r
            while True:
                c += np.uint64(1)
                x = -math.log(uniform53(_draw(fkey, c))) / _ZIG_R
                c += np.uint64(1)
                y = -math.log(uniform53(_draw(fkey, c)))
                if y + y >= x * x:
                    break
            return _ZIG_R + x if hz > 0 else -_ZIG_R - x
        c += np.uint64(1)
        if fn[iz] + uniform53(_draw(fkey, c)) * (fn[iz - 1] - fn[iz]) < math.exp(-0.5 * x * x):
            return x
        c += np.uint64(1)
        h = _draw(fkey, c)
        hz = np.float64(np.int32(h & _LOW32))
        iz = np.int64((h >> np.uint64(32)) & _ZIG_MASK)
        if abs(hz) < kn[iz]:
            return hz * wn[iz]


@nb.njit(**JIT)
def normal_from_bits(value32, layer, fkey, fb):
    """Standard normal from 32 random bits (a signed value) and an 8-bit layer (ziggurat).

    ``fkey`` and ``fb`` (a number unique to this draw) key the fallback stream of the rare slow
    path (about 1 % of draws with these tables, the top layer always included).
    """
    hz = np.float64(np.int32(value32))
    if abs(hz) < _KN[layer]:
        return hz * _WN[layer]
    return _zig_fallback(hz, layer, mix64(np.uint64(fkey) ^ np.uint64(fb)))


@nb.njit(**JIT)
def trial_key(nkey, trial):
    """Key of the noise of one trial: every (trial, point) pair then reads positions
    4 * point .. 4 * point + 3 of a SplitMix64 sequence starting at this key."""
    return mix64(mix64(np.uint64(nkey) + np.uint64(trial) * GAMMA))


@nb.njit(**PJIT)
def trial_keys(nkey, t0, n, out):
    """``trial_key`` of trials t0 .. t0+n-1 into out (n,) uint64."""
    for k in nb.prange(n):
        out[k] = trial_key(nkey, t0 + k)


@nb.njit(**JIT)
def _three_normals(tkey, fkey, point):
    c = np.uint64(point) * np.uint64(4)
    h1 = _draw(tkey, c)
    h2 = _draw(tkey, c + np.uint64(1))
    l0 = np.int64((h2 >> np.uint64(32)) & _ZIG_MASK)
    l1 = np.int64((h2 >> np.uint64(42)) & _ZIG_MASK)
    l2 = np.int64((h2 >> np.uint64(52)) & _ZIG_MASK)
    fb = np.uint64(tkey) + c * GAMMA
    z0 = normal_from_bits(h1 & _LOW32, l0, fkey, fb)
    z1 = normal_from_bits(h1 >> np.uint64(32), l1, fkey, fb + np.uint64(1))
    z2 = normal_from_bits(h2 & _LOW32, l2, fkey, fb + np.uint64(2))
    return z0, z1, z2


@nb.njit(**JIT)
def axis_noise_mm(nkey, fkey, trial, point, sig, speed, tau_code, tau_par, out):
    """Axis-position noise (vibration + reading delay, eq. 9-10) of one (trial, point), mm.

    Parameters
    ----------
    nkey, fkey : uint64
        ``stream_key(seed, STREAM_NOISE)`` and ``stream_key(seed, STREAM_FALLBACK)``.
    trial, point : int
        Trial index (< 2**32) and point index (< 2**30); the draw depends on nothing else.
    sig : ndarray, shape (3,), mm
        Normal std per axis (x, y, z): vibration, combined in quadrature with a normal reading
        delay (the sum of independent normals is normal: same distribution, half the draws).
    speed : ndarray, shape (3,), mm/s
        Speeds for the eq. 9 delay ``speed * tau`` (zeros when the delay is normal).
    tau_code : int
        PDF code of tau (s); -1 for no speed x tau delay.
    tau_par : ndarray, shape (4,)
    out : ndarray, shape (3,), mm
        Receives (n_x, n_y, n_z), to add to the commanded positions.
    """
    _noise_of_trial(trial_key(nkey, trial), fkey, point, sig, speed, tau_code, tau_par, out)


@nb.njit(inline="always", **JIT)
def _noise_of_trial(tkey, fkey, point, sig, speed, tau_code, tau_par, out):
    """`axis_noise_mm` given the trial's key ``tkey = trial_key(nkey, trial)``."""
    z0, z1, z2 = _three_normals(tkey, fkey, point)
    out[0] = sig[0] * z0
    out[1] = sig[1] * z1
    out[2] = sig[2] * z2
    if tau_code >= 0:
        tau = _delay_tau(tkey, point, tau_code, tau_par)
        out[0] += speed[0] * tau
        out[1] += speed[1] * tau
        out[2] += speed[2] * tau


@nb.njit(inline="always", **JIT)
def _delay_tau(tkey, point, tau_code, tau_par):
    """tau (s) of the eq. 9 reading delay of one (trial, point): position 4 * point + 2 of the
    trial's sequence (``tkey = trial_key(nkey, trial)``), the normals taking 4 * point + 0, 1."""
    c = np.uint64(point) * np.uint64(4) + np.uint64(2)
    return pdf_ppf(tau_code, tau_par, uniform53(_draw(tkey, c)))


@nb.njit(inline="always", **JIT)
def _zig_fast3(key, c):
    """Fast path of ``_three_normals`` at counter c (vectorisable): z0, z1, z2 and whether all
    three took it; if not, ``_three_normals`` gives the exact values."""
    h1 = _draw(key, c)
    h2 = _draw(key, c + np.uint64(1))
    l0 = np.int64((h2 >> np.uint64(32)) & _ZIG_MASK)
    l1 = np.int64((h2 >> np.uint64(42)) & _ZIG_MASK)
    l2 = np.int64((h2 >> np.uint64(52)) & _ZIG_MASK)
    v0 = np.float64(np.int32(h1 & _LOW32))
    v1 = np.float64(np.int32(h1 >> np.uint64(32)))
    v2 = np.float64(np.int32(h2 & _LOW32))
    w0 = _ZIG_WORDS[l0]  # scale and threshold of the layer in one word (`packed_layers`)
    w1 = _ZIG_WORDS[l1]
    w2 = _ZIG_WORDS[l2]
    ok = (
        (abs(v0) < np.float64(w0 & _THRESHOLD_MASK) * _THRESHOLD_UNIT)
        & (abs(v1) < np.float64(w1 & _THRESHOLD_MASK) * _THRESHOLD_UNIT)
        & (abs(v2) < np.float64(w2 & _THRESHOLD_MASK) * _THRESHOLD_UNIT)
    )
    return v0 * _float_from_bits(w0), v1 * _float_from_bits(w1), v2 * _float_from_bits(w2), ok


@nb.njit(**JIT)
def normals_by_index(key, fkey, t0, n, z, ok):
    """``_three_normals(key, fkey, t)`` for t = t0 .. t0+n-1 into z (3, >= n), same numbers.

    The fast path (99 % of draws) runs as one vectorised loop; the rest is redone exactly.
    ``ok`` (>= n,) bool is work space.
    """
    for k in range(n):
        z0, z1, z2, good = _zig_fast3(key, np.uint64(t0 + k) * np.uint64(4))
        z[0, k] = z0
        z[1, k] = z1
        z[2, k] = z2
        ok[k] = good
    for k in range(n):
        if not ok[k]:
            z[0, k], z[1, k], z[2, k] = _three_normals(key, fkey, t0 + k)


@nb.njit(**JIT)
def normals_by_key(keys, fkey, point, n, z, ok):
    """``_three_normals(keys[k], fkey, point)`` for k < n into z (3, >= n), same numbers
    (the kinematics layout: one key per trial, a fixed counter per point)."""
    c = np.uint64(point) * np.uint64(4)
    for k in range(n):
        z0, z1, z2, good = _zig_fast3(keys[k], c)
        z[0, k] = z0
        z[1, k] = z1
        z[2, k] = z2
        ok[k] = good
    for k in range(n):
        if not ok[k]:
            z[0, k], z[1, k], z[2, k] = _three_normals(keys[k], fkey, point)
