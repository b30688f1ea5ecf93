"""All numba code of cfm_fem: raw kernels with no I/O and no checks.

Callers validate inputs. Every kernel has a plain-numpy twin (in the module that calls it or in
``tests/twins.py``) that the tests compare it with. Numba options are set once, here.

Sections: counter-based random numbers (shared by every workflow), bench kinematics, point
location and interpolation, order statistics, the field-map sweep.

Random numbers
--------------
Every number is a pure function of (seed, stream, index), so results do not depend on threads,
chunking or the order of evaluation. The generator is SplitMix64 read at a position (state = key
+ counter * gamma, output = Stafford's mix13 finaliser). Normals come from Marsaglia and Tsang's
ziggurat (1024 layers) with independent bits for the value (32) and the layer (10); each
layer's scale and (rounded-down) threshold share one table word (`ziggurat_tables`); the slow
path (about 0.4 % of draws) draws from a separate stream. The kinematics reads one sequence per
seed for the error amplitudes at 32 * trial + k and, for the noise of trial t, positions 4 *
point + slot of a sequence keyed by a double hash of (seed, t) (`trial_key`): consecutive
positions, the way SplitMix64 is meant to be used (a strided counter, e.g. trial << 32, gave
visibly correlated outputs). The sweep keys one sequence per node (`trial_key` of the node
index) and reads positions 4 * trial, 4 * trial + 1 for the three normals of a trial.

Bench kinematics
----------------
Hot loop (constant error profiles): per trial the 21 errors are common to all points, so the
chain collapses exactly (no approximation) to E = C + sum_a q_a G_a + sum_a n_a D_a, with
D_a = (product of the rotations below axis a) d_a, G_a = D_a - e_a and C the offset. The 21
numbers (C, G, D) are computed once per trial; each (point, trial) then costs 3 normals and
18 multiply-adds.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from ._numba_cache import CACHE
from .threads import map_blocks

#: One place for numba options. ``cache`` keeps compile time out of repeated runs.
JIT = dict(nogil=True, cache=CACHE, fastmath=False, error_model="numpy")
PJIT = dict(JIT, parallel=True)
#: Multiply-adds fused where the hardware has them: for loops whose results only need to agree
#: with their twins to rounding (same bits on a given machine, whatever the threads).
FJIT = dict(JIT, fastmath={"contract"})


def kernels_cached(*kernels) -> bool:
    """Whether numba's on-disk cache holds compiled code of each of ``kernels`` for this source.

    False means the next call compiles (tens of seconds for the sweep kernels); the commands
    say so before starting. Reads numba's cache index (a private API): if that fails, True.
    """
    try:
        return all(len(k._cache._cache_file._load_index()) > 0 for k in kernels)
    except Exception:  # another numba version: say nothing rather than something wrong
        return True


# ---------------------------------------------------------------------------------------------
# Random numbers and bench kinematics
# ---------------------------------------------------------------------------------------------
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
    """Inverse CDF of the kernel PDFs (codes in ``cfm_fem.mc.KERNEL_PDF_CODES``).

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
def _cos_sin(x):
    """cos x, sin x (rad): Taylor polynomials within 1 ulp for |x| <= 1/16 (bench error angles
    are ~1e-5 rad: there they equal libm's bits, at a tenth of the cost), libm beyond."""
    if abs(x) > 0.0625:
        return math.cos(x), math.sin(x)
    x2 = x * x
    c = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24.0 + x2 * (-1.0 / 720.0 + x2 * (
        1.0 / 40320.0 - x2 / 3628800.0))))  # fmt: skip
    s = x + x * x2 * (-1.0 / 6.0 + x2 * (1.0 / 120.0 + x2 * (-1.0 / 5040.0 + x2 / 362880.0)))
    return c, s


@nb.njit(inline="always", **JIT)
def rotation_zyx_into(phi, theta, psi, r):
    """Paper eq. 4 into ``r`` (3, 3): Rz(psi) Ry(theta) Rx(phi)."""
    cf, sf = _cos_sin(phi)
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(psi)
    r[0, 0] = cp * ct
    r[0, 1] = cp * sf * st - cf * sp
    r[0, 2] = sf * sp + cf * cp * st
    r[1, 0] = ct * sp
    r[1, 1] = cf * cp + sf * sp * st
    r[1, 2] = cf * sp * st - cp * sf
    r[2, 0] = -st
    r[2, 1] = ct * sf
    r[2, 2] = cf * ct


@nb.njit(inline="always", **JIT)
def _squareness_into(stack, a_xy, a_xz, a_yz, ang):
    """Zyx angles per bench axis (ang[a, :]) for the squareness convention of kinematics.py."""
    for a in range(3):
        for c in range(3):
            ang[a, c] = 0.0
    level = np.empty(3, np.int64)
    for j in range(3):
        level[stack[j]] = j
    for col in range(3):
        if col == 0:
            a, b, alpha = 0, 1, a_xy
        elif col == 1:
            a, b, alpha = 0, 2, a_xz
        else:
            a, b, alpha = 1, 2, a_yz
        if level[a] > level[b]:
            up, lo = a, b
        else:
            up, lo = b, a
        c = 3 - a - b
        cyclic = (up == 0 and lo == 1) or (up == 1 and lo == 2) or (up == 2 and lo == 0)
        ang[up, c] += alpha if cyclic else -alpha


@nb.njit(**JIT)
def _tilt(stack, a, a_xy, a_xz, a_yz):
    """Zyx angles (phi, theta, psi) tilting axis a's travel direction (``_squareness_into``)."""
    lx = 0
    ly = 0
    lz = 0
    for j in range(3):
        if stack[j] == 0:
            lx = j
        elif stack[j] == 1:
            ly = j
        else:
            lz = j
    ang0 = 0.0
    ang1 = 0.0
    ang2 = 0.0
    # pair (x, y) -> about z; (x, z) -> about y; (y, z) -> about x; the upper axis is tilted
    for col in range(3):
        if col == 0:
            p, q, alpha, lp, lq = 0, 1, a_xy, lx, ly
        elif col == 1:
            p, q, alpha, lp, lq = 0, 2, a_xz, lx, lz
        else:
            p, q, alpha, lp, lq = 1, 2, a_yz, ly, lz
        up, lo = (p, q) if lp > lq else (q, p)
        if up != a:
            continue
        c = 3 - p - q
        cyclic = (up == 0 and lo == 1) or (up == 1 and lo == 2) or (up == 2 and lo == 0)
        sgn = alpha if cyclic else -alpha
        if c == 0:
            ang0 += sgn
        elif c == 1:
            ang1 += sgn
        else:
            ang2 += sgn
    return ang0, ang1, ang2


@nb.njit(inline="always", **JIT)
def _rot_apply(phi, theta, psi, v0, v1, v2):
    """R(phi, theta, psi) of eq. 4 applied to (v0, v1, v2), without building the matrix."""
    cf, sf = _cos_sin(phi)
    ct, st = _cos_sin(theta)
    cp, sp = _cos_sin(psi)
    w0 = cp * ct * v0 + (cp * sf * st - cf * sp) * v1 + (sf * sp + cf * cp * st) * v2
    w1 = ct * sp * v0 + (cf * cp + sf * sp * st) * v1 + (cf * sp * st - cp * sf) * v2
    w2 = -st * v0 + ct * sf * v1 + cf * ct * v2
    return w0, w1, w2


@nb.njit(inline="always", **JIT)
def _horner(profiles, k, u):
    p = 0.0
    for c in range(profiles.shape[1] - 1, -1, -1):
        p = p * u + profiles[k, c]
    return p


@nb.njit(inline="always", **JIT)
def probe_error_mm(params, q_cmd, dq, stack, mounts, tool, strokes, profiles, out):
    """Probe position error of one (point, trial): exact HTM chain (eq. 4, 5, 8, 10), bench frame.

    Callable from the user's own ``@njit`` code, once per (node, trial).

    Parameters
    ----------
    params : ndarray, shape (21,)
        Error amplitudes of this trial (mm, rad) in ``cfm_fem.bench.ERROR_NAMES`` order: one row
        of ``cfm_fem.kinematics.draw_error_sets``.
    q_cmd : ndarray, shape (3,), mm
        Commanded positions of the x, y, z axes (``Bench.axis_positions_for``).
    dq : ndarray, shape (3,), mm
        Vibration + delay added to the commanded positions (``axis_noise_mm``), or zeros.
    stack : ndarray, shape (3,), int64
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3 from the foundation.
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
        Probe offset in the top carriage frame.
    strokes : ndarray, shape (3,), mm
        Strokes of the x, y, z axes (normalise the profile argument).
    profiles : ndarray, shape (21, n_coef)
        Polynomial profile coefficients of the errors.
    out : ndarray, shape (3,), mm
        Receives E = P_actual - P_nominal.
    """
    # Walk the chain from the tool down: v <- m_j + (q+n) d_j + delta_j + R_j v (no allocation:
    # this runs once per (node, trial) inside the caller's loops).
    v0 = tool[0]
    v1 = tool[1]
    v2 = tool[2]
    for jj in range(2, -1, -1):
        a = stack[jj]
        d0, d1, d2 = _travel_direction(stack, a, params)
        v0, v1, v2 = _body_step(params, q_cmd, dq, jj, a, d0, d1, d2, mounts, strokes, profiles,
                                v0, v1, v2)  # fmt: skip
    _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out)


@nb.njit(inline="always", **JIT)
def _travel_direction(stack, a, params):
    """Travel direction of axis a, tilted by the squareness errors params[18:21] (unit vector)."""
    t0, t1, t2 = _tilt(stack, a, params[18], params[19], params[20])
    return _rot_apply(
        t0, t1, t2, 1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0, 1.0 if a == 2 else 0.0
    )


@nb.njit(inline="always", **JIT)
def _body_step(params, q_cmd, dq, jj, a, d0, d1, d2, mounts, strokes, profiles, v0, v1, v2):
    """One body of the chain: m_j + (q + n) d_j + delta_j(q) + R_j(q) v, for body jj (axis a,
    travel direction d)."""
    base = 6 * a
    u = q_cmd[a] / strokes[a]
    ex = params[base + 3] * _horner(profiles, base + 3, u)
    ey = params[base + 4] * _horner(profiles, base + 4, u)
    ez = params[base + 5] * _horner(profiles, base + 5, u)
    w0, w1, w2 = _rot_apply(ex, ey, ez, v0, v1, v2)
    s = q_cmd[a] + dq[a]
    return (
        mounts[jj, 0] + s * d0 + params[base] * _horner(profiles, base, u) + w0,
        mounts[jj, 1] + s * d1 + params[base + 1] * _horner(profiles, base + 1, u) + w1,
        mounts[jj, 2] + s * d2 + params[base + 2] * _horner(profiles, base + 2, u) + w2,
    )


@nb.njit(inline="always", **JIT)
def _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out):
    """out = the probe position v minus the nominal one (mounts + q + tool)."""
    out[0] = v0 - (mounts[0, 0] + mounts[1, 0] + mounts[2, 0] + q_cmd[0] + tool[0])
    out[1] = v1 - (mounts[0, 1] + mounts[1, 1] + mounts[2, 1] + q_cmd[1] + tool[1])
    out[2] = v2 - (mounts[0, 2] + mounts[1, 2] + mounts[2, 2] + q_cmd[2] + tool[2])


@nb.njit(inline="always", **JIT)
def _probe_error_directed(params, q_cmd, dq, dirs, stack, mounts, tool, strokes, profiles, out):
    """`probe_error_mm` with the trial's travel directions given (dirs (9,): axis a's at
    3a .. 3a+2, `trial_directions`): the same numbers, without recomputing them per point."""
    v0 = tool[0]
    v1 = tool[1]
    v2 = tool[2]
    for jj in range(2, -1, -1):
        a = stack[jj]
        v0, v1, v2 = _body_step(params, q_cmd, dq, jj, a, dirs[3 * a], dirs[3 * a + 1],
                                dirs[3 * a + 2], mounts, strokes, profiles, v0, v1, v2)  # fmt: skip
    _minus_nominal(v0, v1, v2, q_cmd, mounts, tool, out)


@nb.njit(**PJIT)
def trial_directions(params, stack, out):
    """Travel directions of the x, y, z axes of each trial (``_travel_direction``) into out
    (m, 9): axis a's at 3a .. 3a+2."""
    for t in nb.prange(params.shape[0]):
        for a in range(3):
            out[t, 3 * a], out[t, 3 * a + 1], out[t, 3 * a + 2] = _travel_direction(
                stack, a, params[t]
            )


@nb.njit(**PJIT)
def trial_terms(params, stack, mounts, tool, out):
    """Per-trial constants of the collapsed chain (constant profiles only), into out (m, 21).

    out[t] = (C, G_x, G_y, G_z, D_x, D_y, D_z) with E = C + sum_a q_a G_a + sum_a n_a D_a exactly
    (module docstring). Same math as ``probe_error_mm``.
    """
    m = params.shape[0]
    nchunk = 64  # fixed layout: scratch arrays once per chunk, not per trial
    per = (m + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        r = np.empty((3, 3))
        rs = np.empty((3, 3))
        a_acc = np.empty((3, 3))
        tmp = np.empty((3, 3))
        ang = np.empty((3, 3))
        cc = np.empty(3)
        for t in range(ch * per, min(m, (ch + 1) * per)):
            p = params[t]
            for i in range(3):
                cc[i] = 0.0
                for k in range(3):
                    a_acc[i, k] = 1.0 if i == k else 0.0
            _squareness_into(stack, p[18], p[19], p[20], ang)
            for j in range(3):
                a = stack[j]
                base = 6 * a
                rotation_zyx_into(ang[a, 0], ang[a, 1], ang[a, 2], rs)
                # D_a = A_j d_a (A_j: product of the error rotations below body j)
                for i in range(3):
                    d = a_acc[i, 0] * rs[0, a] + a_acc[i, 1] * rs[1, a] + a_acc[i, 2] * rs[2, a]
                    out[t, 12 + 3 * a + i] = d
                    out[t, 3 + 3 * a + i] = d - (1.0 if i == a else 0.0)
                # C += A_j (m_j + delta_j) - m_j
                v0 = mounts[j, 0] + p[base]
                v1 = mounts[j, 1] + p[base + 1]
                v2 = mounts[j, 2] + p[base + 2]
                for i in range(3):
                    cc[i] += a_acc[i, 0] * v0 + a_acc[i, 1] * v1 + a_acc[i, 2] * v2 - mounts[j, i]
                rotation_zyx_into(p[base + 3], p[base + 4], p[base + 5], r)
                for i in range(3):
                    for k in range(3):
                        tmp[i, k] = (
                            a_acc[i, 0] * r[0, k] + a_acc[i, 1] * r[1, k] + a_acc[i, 2] * r[2, k]
                        )
                for i in range(3):
                    for k in range(3):
                        a_acc[i, k] = tmp[i, k]
            # the tool through all three rotations, minus the nominal tool
            for i in range(3):
                out[t, i] = (
                    cc[i]
                    + a_acc[i, 0] * tool[0]
                    + a_acc[i, 1] * tool[1]
                    + a_acc[i, 2] * tool[2]
                    - tool[i]
                )


# ------------------------------------------------------------------------------------------
# Monte Carlo passes over (point, trial). Parallel over points; each point sees the trials of a
# block in increasing order, so sums and counts are bit-identical whatever the number of threads.
# Per (point, block): fill the values E_x, E_y, E_z, |E| of the block's trials (the hot loop),
# then reduce them in separate loops (vectorisable sums and counts, rare window work).
# ------------------------------------------------------------------------------------------

N_QTY = 4  # quantities per point: E_x, E_y, E_z, |E|
#: Reductions may be reassociated (vectorised); the order is fixed by the compiled code.
_RJIT = dict(JIT, fastmath={"reassoc"})


@nb.njit(**JIT)
def fill_values(model, t0, n, q, i, pi, ev):
    """Values of point i (index pi) for trials t0..t0+n-1 into ev (4, >= n): E_x, E_y, E_z, |E|.

    model: the tuple of ``_Engine.model`` (linear, terms, params, sig, speed, tau_code, tau_par,
    nkey, tkeys, fkey, stack, mounts, tool, strokes, profiles, dirs), rows 0 .. n-1 of terms,
    params, tkeys and dirs (`trial_directions`, non-linear models) being trials t0 .. t0+n-1.
    ``linear`` with ``tau_code < 0`` is the hot path (collapsed chain, three normals); otherwise
    ``probe_error_mm`` (with the trial's directions) / the collapsed chain with the noise of
    ``axis_noise_mm``. Both give the same numbers for the same (seed, trial, point).
    """
    linear, terms, params, sig, speed, tau_code, tau_par, _, tkeys, fkey = model[:10]
    if linear and tau_code < 0:
        s0 = sig[0]
        s1 = sig[1]
        s2 = sig[2]
        q0 = q[i, 0]
        q1 = q[i, 1]
        q2 = q[i, 2]
        # the normals first (vectorised fast path, same numbers as `_three_normals`), then the
        # chain in a loop without calls (vectorised too)
        z = np.empty((3, n))
        normals_by_key(tkeys, fkey, pi, n, z, np.empty(n, dtype=np.bool_))
        for k in range(n):
            ev[0, k], ev[1, k], ev[2, k], ev[3, k] = _chain(
                terms, k, q0, q1, q2, s0 * z[0, k], s1 * z[1, k], s2 * z[2, k]
            )
    else:
        stack, mounts, tool, strokes, profiles, dirs = model[10:]
        e = np.empty(3)
        dq = np.empty(3)
        qi = q[i]
        for k in range(n):
            _noise_of_trial(tkeys[k], fkey, pi, sig, speed, tau_code, tau_par, dq)
            if linear:
                e[0], e[1], e[2], _ = _chain(terms, k, qi[0], qi[1], qi[2], dq[0], dq[1], dq[2])
            else:
                _probe_error_directed(params[k], qi, dq, dirs[k], stack, mounts, tool, strokes,
                                      profiles, e)  # fmt: skip
            ev[0, k] = e[0]
            ev[1, k] = e[1]
            ev[2, k] = e[2]
            ev[3, k] = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])


@nb.njit(**_RJIT)
def _sums_below(v, n, shift, lo0, lo1):
    """sum (v - shift), sum (v - shift)^2, #(v < lo0), #(v < lo1) over v[:n]."""
    s = 0.0
    s2 = 0.0
    b0 = 0
    b1 = 0
    for k in range(n):
        d = v[k] - shift
        s += d
        s2 += d * d
        b0 += v[k] < lo0
        b1 += v[k] < lo1
    return s, s2, b0, b1


@nb.njit(inline="always", **JIT)
def _slot(v, lo, inv):
    """Window slot of v (the same expression in both passes): floor((v - lo) * inv)."""
    return (v - lo) * inv


@nb.njit(**JIT)
def _hits(v, a, b, lo0, hi0, lo1, hi1):
    """Number of v[a:b] inside [lo0, hi0] or [lo1, hi1] (a vectorised pre-scan)."""
    h = 0
    for k in range(a, b):
        x = v[k]
        h += ((x >= lo0) & (x <= hi0)) | ((x >= lo1) & (x <= hi1))
    return h


@nb.njit(**JIT)
def _count_windows(v, n, lo0, inv0, lo1, inv1, wh0, wh1):
    """Add the v[:n] that fall in the slots of window 0 (low end) or 1 (high end)."""
    nw = wh0.shape[0]
    top0 = lo0 + (nw + 1) / inv0  # above this, window 0 cannot be hit (one slot of slack)
    for k in range(n):
        x = v[k]
        if x < top0:
            y = _slot(x, lo0, inv0)
            if y >= 0.0 and y < nw:
                wh0[np.int64(y)] += 1
        if x >= lo1:
            y = _slot(x, lo1, inv1)
            if y >= 0.0 and y < nw:
                wh1[np.int64(y)] += 1


@nb.njit(**PJIT)
def pass_pilot(model, t0, n, q, pidx, out):
    """Values of trials t0..t0+n-1 into out (npts, 4, n); ``model`` as `fill_values`."""
    for i in nb.prange(q.shape[0]):
        fill_values(model, t0, n, q, i, pidx[i], out[i])


@nb.njit(**PJIT)
def pass_pilot_quantiles(model, t0, n, q, pidx, kth, out):
    """Order statistics ``kth`` (0-based, sorted) of trials t0..t0+n-1 per point and quantity,
    into out (npts, 4, len(kth)), plus the mean in out[..., -1] (one point's values at a time,
    so a large pilot needs no trials x points memory); ``model`` as `fill_values`."""
    npts = q.shape[0]
    nchunk = min(npts, 64)  # one scratch array per chunk of points, not per point
    per = (npts + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        ev = np.empty((4, n))
        for i in range(ch * per, min(npts, (ch + 1) * per)):
            _pilot_point(model, t0, n, q, i, pidx[i], kth, out, ev)


@nb.njit(**JIT)
def _pilot_point(model, t0, n, q, i, pi, kth, out, ev):
    """Pilot order statistics and mean of point i (scratch ev (4, n) reused across points)."""
    fill_values(model, t0, n, q, i, pi, ev)
    # kth = (low end: lower, upper bracket; high end: lower, upper; 0; n - 1). The brackets only
    # place windows, so a histogram of the pilot with conservative bin edges is enough (a
    # selection per bracket costs several times more).
    nb_ = 2048
    counts = np.empty(nb_, np.int64)
    for c in range(4):
        v = ev[c]
        vmin = v[:n].min()
        vmax = v[:n].max()
        out[i, c, 4] = vmin
        out[i, c, 5] = vmax
        out[i, c, 6] = v[:n].mean()
        width = (vmax - vmin) / nb_
        if not width > 0.0:
            for j in range(4):
                out[i, c, j] = vmin
            continue
        counts[:] = 0
        inv = 1.0 / width
        for k in range(n):
            b = min(np.int64((v[k] - vmin) * inv), nb_ - 1)
            counts[b] += 1
        for j in range(4):
            r = kth[j] + 1  # 1-based rank
            cum = 0
            b = 0
            while cum + counts[b] < r:
                cum += counts[b]
                b += 1
            # lower brackets take the bin's lower edge, upper brackets its upper edge
            out[i, c, j] = vmin + (b if j % 2 == 0 else b + 1) * width


@nb.njit(**PJIT)
def pass_window(model, t0, n, q, pidx, shift, wlo, winv, acc, below, whist):
    """Pass 1 of the generic path: shifted sums, and counts around each interval end, over
    trials t0..t0+n-1.

    acc (npts, 4, 2): sum of (v - shift) and of (v - shift)**2 per quantity (shift: a pilot
    mean, which keeps the variance free of cancellation). For each point, quantity c and
    interval end s, a window of W slots [wlo, wlo + W / winv): below[i, c, s] counts values under
    it, whist[i, c, s, k] values in slot k (floor((v - wlo) * winv) == k). ``model`` as
    `fill_values`.
    """
    for i in nb.prange(q.shape[0]):
        ev = np.empty((4, n))
        fill_values(model, t0, n, q, i, pidx[i], ev)
        for c in range(4):
            a, b, c0, c1 = _sums_below(ev[c], n, shift[i, c], wlo[i, c, 0], wlo[i, c, 1])
            acc[i, c, 0] += a
            acc[i, c, 1] += b
            below[i, c, 0] += c0
            below[i, c, 1] += c1
            _count_windows(
                ev[c],
                n,
                wlo[i, c, 0],
                winv[i, c, 0],
                wlo[i, c, 1],
                winv[i, c, 1],
                whist[i, c, 0],
                whist[i, c, 1],
            )


@nb.njit(**JIT)
def _keep(v, n, i, c, vlo, vhi, wlo, winv, target, offset, fill, buf):
    """Append to buf the v[:n] in the target slot of either interval end of quantity c."""
    lo0 = vlo[i, c, 0]
    hi0 = vhi[i, c, 0]
    lo1 = vlo[i, c, 1]
    hi1 = vhi[i, c, 1]
    for a in range(0, n, 256):  # most stretches of 256 values hold no candidate at all
        b = min(n, a + 256)
        if _hits(v, a, b, lo0, hi0, lo1, hi1) == 0:
            continue
        for k in range(a, b):
            x = v[k]
            # range pre-tests; the slot index, computed as in pass 1, decides
            if x >= lo0 and x <= hi0:
                y = _slot(x, wlo[i, c, 0], winv[i, c, 0])
                if y >= 0.0 and np.int64(y) == target[i, c, 0]:
                    buf[offset[i, c, 0] + fill[i, c, 0]] = x
                    fill[i, c, 0] += 1
            if x >= lo1 and x <= hi1:
                y = _slot(x, wlo[i, c, 1], winv[i, c, 1])
                if y >= 0.0 and np.int64(y) == target[i, c, 1]:
                    buf[offset[i, c, 1] + fill[i, c, 1]] = x
                    fill[i, c, 1] += 1


@nb.njit(**PJIT)
def pass_capture(model, t0, n, q, pidx, wlo, winv, target, vlo, vhi, offset, fill, buf):
    """Pass 2: keep the values in window slot target[i, c, s] (exact order statistics).

    vlo, vhi (npts, 4, 2): that slot's value range widened by a few ulps (pre-test);
    offset (npts, 4, 2): start of each capture in buf; fill: values stored so far. ``model`` as
    `fill_values`.
    """
    for i in nb.prange(q.shape[0]):
        ev = np.empty((4, n))
        fill_values(model, t0, n, q, i, pidx[i], ev)
        for c in range(4):
            _keep(ev[c], n, i, c, vlo, vhi, wlo, winv, target, offset, fill, buf)


# ------------------------------------------------------------------------------------------
# Hot path of the kinematics (constant profiles, normal noise): one pass over the trials, fused
# per point and sub-block of SUB trials (the 21 chain terms of a sub-block stay in cache while a
# chunk of points uses them). Per (point, sub-block): the values (one vectorised loop; the ~1.3 %
# of samples with a slow-path normal are redone exactly), then sums, counts below each
# interval-end window and a flag per sample inside some window (one vectorised loop), then the
# flagged values are kept in their windows' stores. The point loop is one function with the
# value loop inlined: a call per (point, sub-block) cost ~0.5 ns per sample. Loops index with
# unsigned integers where a signed index costs a wrap-around test that stops vectorisation.
# ------------------------------------------------------------------------------------------
#: Trials per sub-block of the fused pass.
SUB = 512
#: Points per parallel chunk; the chunking does not change any number.
_N_CHUNKS = 64
#: Bit 0 of each byte: a bool array read eight entries at a time.
_BYTE_ONES = np.uint64(0x0101010101010101)


@nb.njit(inline="always", **JIT)
def _chain(terms, k, q0, q1, q2, n0, n1, n2):
    """E_x, E_y, E_z, |E| of trial row k of ``terms`` at commanded q and axis noise n (mm).

    The one expression of the collapsed chain: every path must produce the same bits for the
    same sample (no FMA contraction: fastmath is off)."""
    e0 = (terms[k, 0] + q0 * terms[k, 3] + q1 * terms[k, 6] + q2 * terms[k, 9]
          + n0 * terms[k, 12] + n1 * terms[k, 15] + n2 * terms[k, 18])  # fmt: skip
    e1 = (terms[k, 1] + q0 * terms[k, 4] + q1 * terms[k, 7] + q2 * terms[k, 10]
          + n0 * terms[k, 13] + n1 * terms[k, 16] + n2 * terms[k, 19])  # fmt: skip
    e2 = (terms[k, 2] + q0 * terms[k, 5] + q1 * terms[k, 8] + q2 * terms[k, 11]
          + n0 * terms[k, 14] + n1 * terms[k, 17] + n2 * terms[k, 20])  # fmt: skip
    return e0, e1, e2, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)


@nb.njit(inline="always", **JIT)
def _bit_index(low):
    """Index of the single set bit of ``low`` (a power of two, uint64)."""
    return _DEBRUIJN_INDEX[np.int64((low * _DEBRUIJN) >> np.uint64(58))]


@nb.njit(**JIT)
def _redo_sample(terms, tkeys, k, q0, q1, q2, s0, s1, s2, fkey, pi, ev, j):
    """Exact values (slow-path normals included) of trial row k of point pi into ev[:, j]."""
    z0, z1, z2 = _three_normals(tkeys[k], fkey, pi)
    ev[0, j], ev[1, j], ev[2, j], ev[3, j] = _chain(terms, k, q0, q1, q2, s0 * z0, s1 * z1, s2 * z2)


@nb.njit(inline="always", **JIT)
def _values_run(terms, tkeys, k0, m, q0, q1, q2, s0, s1, s2, fkey, pi, ev, ok, okw):
    """Values of point pi for the trial rows k0 .. k0+m-1 into ev (4, SUB): E_x, E_y, E_z, |E|.

    One vectorised loop takes the ziggurat's fast path (`_zig_fast3`); the samples with a
    slow-path normal (~1.3 %) are found eight flags at a time through ``okw`` (``ok``'s bytes as
    uint64, SUB // 8) and redone exactly: the numbers of ``fill_values``."""
    c = np.uint64(pi) * np.uint64(4)
    e0 = ev[0]  # row views: stores through the 2-D array kept the loop scalar
    e1 = ev[1]
    e2 = ev[2]
    e3 = ev[3]
    for j in range(m):
        k = np.uint64(k0) + np.uint64(j)
        z0, z1, z2, good = _zig_fast3(tkeys[k], c)
        e0[j], e1[j], e2[j], e3[j] = _chain(terms, k, q0, q1, q2, s0 * z0, s1 * z1, s2 * z2)
        ok[j] = good
    for w in range((m + 7) >> 3):
        bad = ~okw[w] & _BYTE_ONES
        while bad != 0:
            low = bad & (~bad + np.uint64(1))
            bad ^= low
            j = (w << 3) + (_bit_index(low) >> 3)
            if j < m:
                _redo_sample(terms, tkeys, k0 + j, q0, q1, q2, s0, s1, s2, fkey, pi, ev, j)


@nb.njit(**_RJIT)
def _sums_flags(ev, m, i, shift, lo, hi, out, flag):
    """Sums, counts below each window and window flags of ev[:, :m] (one vectorised loop).

    For point i: shift (npts, 4); lo, hi (npts, 4, 2): window (c, e) is [lo, hi]. Adds to out
    (4, 4), per quantity c: sum (v - shift), sum (v - shift)^2, #(v < lo[i, c, 0]),
    #(v < lo[i, c, 1]). flag[j] (uint8): bit 2c + e set when sample j lies in window (c, e).
    """
    e0 = ev[0]
    e1 = ev[1]
    e2 = ev[2]
    e3 = ev[3]
    a0 = a1 = a2 = a3 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    c00 = c01 = c10 = c11 = c20 = c21 = c30 = c31 = 0
    h0, h1, h2, h3 = shift[i, 0], shift[i, 1], shift[i, 2], shift[i, 3]
    l00, l01, l10, l11 = lo[i, 0, 0], lo[i, 0, 1], lo[i, 1, 0], lo[i, 1, 1]
    l20, l21, l30, l31 = lo[i, 2, 0], lo[i, 2, 1], lo[i, 3, 0], lo[i, 3, 1]
    u00, u01, u10, u11 = hi[i, 0, 0], hi[i, 0, 1], hi[i, 1, 0], hi[i, 1, 1]
    u20, u21, u30, u31 = hi[i, 2, 0], hi[i, 2, 1], hi[i, 3, 0], hi[i, 3, 1]
    for j in range(m):
        x0 = e0[j]
        x1 = e1[j]
        x2 = e2[j]
        x3 = e3[j]
        d0 = x0 - h0
        d1 = x1 - h1
        d2 = x2 - h2
        d3 = x3 - h3
        a0 += d0
        a1 += d1
        a2 += d2
        a3 += d3
        b0 += d0 * d0
        b1 += d1 * d1
        b2 += d2 * d2
        b3 += d3 * d3
        c00 += x0 < l00
        c01 += x0 < l01
        c10 += x1 < l10
        c11 += x1 < l11
        c20 += x2 < l20
        c21 += x2 < l21
        c30 += x3 < l30
        c31 += x3 < l31
        flag[j] = (
            np.uint8((x0 >= l00) & (x0 <= u00))
            | np.uint8((x0 >= l01) & (x0 <= u01)) << np.uint8(1)
            | np.uint8((x1 >= l10) & (x1 <= u10)) << np.uint8(2)
            | np.uint8((x1 >= l11) & (x1 <= u11)) << np.uint8(3)
            | np.uint8((x2 >= l20) & (x2 <= u20)) << np.uint8(4)
            | np.uint8((x2 >= l21) & (x2 <= u21)) << np.uint8(5)
            | np.uint8((x3 >= l30) & (x3 <= u30)) << np.uint8(6)
            | np.uint8((x3 >= l31) & (x3 <= u31)) << np.uint8(7)
        )  # fmt: skip
    out[0, 0] += a0
    out[1, 0] += a1
    out[2, 0] += a2
    out[3, 0] += a3
    out[0, 1] += b0
    out[1, 1] += b1
    out[2, 1] += b2
    out[3, 1] += b3
    out[0, 2] += c00
    out[0, 3] += c01
    out[1, 2] += c10
    out[1, 3] += c11
    out[2, 2] += c20
    out[2, 3] += c21
    out[3, 2] += c30
    out[3, 3] += c31


@nb.njit(inline="always", **JIT)
def _keep_flagged(ev, flagw, m, i, lo, hi, store, off, cap, fill):
    """Append each flagged value to the stores of the windows its flag names.

    ``flagw``: the flags (`_sums_flags`) eight at a time as uint64. Window (i, c, e) owns
    store[off : off + cap + 1] and counts its values in fill, stored while fill <= cap (fill >
    cap: overflow, the window is lost); a value is written at the next free place, the spare
    last one once full (no branch on the capacity)."""
    for w in range((m + 7) >> 3):
        hits = flagw[w]
        while hits != 0:
            low = hits & (~hits + np.uint64(1))
            sh = np.uint64(_bit_index(low) & ~7)  # the byte of the first flagged sample
            mk = (hits >> sh) & np.uint64(255)
            hits ^= mk << sh
            j = (w << 3) + np.int64(sh >> np.uint64(3))
            if j >= m:  # bytes past the sub-block's end hold an earlier point's flags
                break
            while mk != 0:
                lb = mk & (~mk + np.uint64(1))
                mk ^= lb
                b = _bit_index(lb)
                c = b >> 1
                e = b & 1
                f = fill[i, c, e]
                store[off[i, c, e] + min(f, cap[i, c, e])] = ev[c, j]
                fill[i, c, e] = f + 1


@nb.njit(inline="always", **JIT)
def _count_and_keep(ev, m, i, shift, lo, hi, acc, below, store, off, cap, fill, red, flag,
                    flagw):  # fmt: skip
    """The values ev[:, :m] of point i (a sub-block) into its sums, counts below the windows and
    window stores (`_sums_flags`, `_keep_flagged`); red (4, 4), flag / flagw: work space."""
    red[:] = 0.0
    _sums_flags(ev, m, i, shift, lo, hi, red, flag)
    for c in range(4):
        acc[i, c, 0] += red[c, 0]
        acc[i, c, 1] += red[c, 1]
        below[i, c, 0] += np.int64(red[c, 2])
        below[i, c, 1] += np.int64(red[c, 3])
    _keep_flagged(ev, flagw, m, i, lo, hi, store, off, cap, fill)


@nb.njit(**PJIT)
def pass_keep(terms, n, q, pidx, sig, tkeys, fkey, shift, lo, hi, acc, below, store, off, cap,
              fill):  # fmt: skip
    """The fused pass over trial rows 0 .. n-1 of a block (hot path).

    Parameters
    ----------
    terms : ndarray (>= n, 21), column-major
        Collapsed chain terms (`trial_terms`) of the block's trials.
    q : ndarray (npts, 3), mm; pidx : ndarray (npts,) int64
        Commanded positions and the points' indices (keys of their noise).
    sig : ndarray (3,), mm
        Normal noise std per axis.
    tkeys : ndarray (>= n,) uint64
        `trial_key` of the block's trials; fkey: the fallback stream's key.
    shift : ndarray (npts, 4)
        Shifts of the sums (a pilot mean: no cancellation in the variance).
    lo, hi : ndarray (npts, 4, 2)
        Interval-end window (c, e): values in [lo, hi] are kept, those below lo counted.
    acc : ndarray (npts, 4, 2)
        Adds sum (v - shift) and sum (v - shift)**2; below (npts, 4, 2) int64: adds #(v < lo).
    store, off, cap, fill
        The windows' stores (`_keep_flagged`).

    Each point sees the trials in increasing order in sub-blocks of SUB: sums and counts are
    the same whatever the number of threads.
    """
    npts = q.shape[0]
    nchunk = min(npts, _N_CHUNKS)
    per = (npts + nchunk - 1) // nchunk
    s0 = sig[0]
    s1 = sig[1]
    s2 = sig[2]
    for ch in nb.prange(nchunk):
        ev = np.empty((4, SUB))
        okw = np.empty(SUB // 8, dtype=np.uint64)
        ok = okw.view(np.bool_)
        flagw = np.empty(SUB // 8, dtype=np.uint64)
        flag = flagw.view(np.uint8)
        red = np.empty((4, 4))
        for k0 in range(0, n, SUB):
            m = min(SUB, n - k0)
            for i in range(ch * per, min(npts, (ch + 1) * per)):
                _values_run(terms, tkeys, k0, m, q[i, 0], q[i, 1], q[i, 2], s0, s1, s2, fkey,
                            pidx[i], ev, ok, okw)  # fmt: skip
                _count_and_keep(ev, m, i, shift, lo, hi, acc, below, store, off, cap, fill, red,
                                flag, flagw)  # fmt: skip


@nb.njit(**PJIT)
def pass_keep_model(model, t0, n, q, pidx, shift, lo, hi, acc, below, store, off, cap, fill):
    """`pass_keep` for any bench model (``model`` as `fill_values`: position-dependent errors,
    speed x tau delay): each point's values of the block by `fill_values`, then its sums,
    counts and kept values by sub-blocks of SUB trials as `pass_keep`. Arguments as
    `pass_keep`; trials t0 .. t0+n-1 are rows 0 .. n-1 of the model's arrays."""
    npts = q.shape[0]
    nchunk = min(npts, _N_CHUNKS)
    per = (npts + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        ev = np.empty((4, n))
        sub = np.empty((4, SUB))
        flagw = np.empty(SUB // 8, dtype=np.uint64)
        flag = flagw.view(np.uint8)
        red = np.empty((4, 4))
        for i in range(ch * per, min(npts, (ch + 1) * per)):
            fill_values(model, t0, n, q, i, pidx[i], ev)
            for k0 in range(0, n, SUB):
                m = min(SUB, n - k0)
                for c in range(4):
                    for j in range(m):
                        sub[c, j] = ev[c, k0 + j]
                _count_and_keep(sub, m, i, shift, lo, hi, acc, below, store, off, cap, fill,
                                red, flag, flagw)  # fmt: skip


#: Histogram bins of a window's values when it narrows (`narrow_windows`).
NARROW_BINS = 256


@nb.njit(**PJIT)
def narrow_windows(store, off, cap, fill, below, lo, hi, klo, khi):
    """Shrink each window to the values that can still hold its order statistic (flat arrays
    over the windows, shape (nw,)).

    A window holds in store[off : off + fill] the values in [lo, hi] of the trials seen so far
    and counts in ``below`` those under lo. Ranks klo <= khi (1-based, among the trials seen)
    must stay inside: the new lo is the smallest stored value of the histogram bin holding rank
    klo, the new hi the largest of the bin holding rank khi (a rank outside the stored ones
    leaves that edge). Values outside are dropped, those under the new lo added to ``below``.
    Windows that overflowed (fill > cap) or hold nothing are left alone.
    """
    nw = fill.shape[0]
    nchunk = min(nw, 256)
    per = (nw + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        cnt = np.empty(NARROW_BINS, np.int64)
        vmin = np.empty(NARROW_BINS)
        vmax = np.empty(NARROW_BINS)
        for w in range(ch * per, min(nw, (ch + 1) * per)):
            f = fill[w]
            a = lo[w]
            b = hi[w]
            kl = klo[w] - below[w]
            kh = khi[w] - below[w]
            if f > cap[w] or f == 0 or not b > a or (kl <= 1 and kh >= f):
                continue
            o = off[w]
            inv = NARROW_BINS / (b - a)
            cnt[:] = 0
            vmin[:] = np.inf
            vmax[:] = -np.inf
            for t in range(f):
                v = store[o + t]
                k = min(np.int64((v - a) * inv), NARROW_BINS - 1)
                cnt[k] += 1
                vmin[k] = min(vmin[k], v)
                vmax[k] = max(vmax[k], v)
            new_lo = a
            new_hi = b
            cum = 0
            for k in range(NARROW_BINS):
                if cum < kl <= cum + cnt[k] and kl > 1:
                    new_lo = vmin[k]
                if cum < kh <= cum + cnt[k] and kh < f:
                    new_hi = vmax[k]
                cum += cnt[k]
            kept = 0
            under = 0
            for t in range(f):  # in place, branch-free: a kept value moves down or stays
                v = store[o + t]
                under += v < new_lo
                store[o + kept] = v
                kept += (v >= new_lo) & (v <= new_hi)
            fill[w] = kept
            below[w] += under
            lo[w] = new_lo
            hi[w] = new_hi


@nb.njit(**PJIT)
def select_ends(store, off, fill, cap, below, lo, hi, rank, out):
    """Order statistic of 1-based rank rank[w] among all trials, per window (flat arrays).

    It is the (rank - below)-th smallest stored value (all in [lo, hi]) when that lies among
    the stored ones and the window did not overflow; otherwise out[w] = NaN (the caller
    recomputes that point). A histogram of NARROW_BINS bins finds the bin holding the rank;
    that bin's values are moved to the front of the store and selected among (three cheap
    passes instead of a selection over all: 3x faster). The stores are overwritten."""
    nw = fill.shape[0]
    nchunk = min(nw, 256)
    per = (nw + nchunk - 1) // nchunk
    for ch in nb.prange(nchunk):
        cnt = np.empty(NARROW_BINS, np.int64)
        for w in range(ch * per, min(nw, (ch + 1) * per)):
            f = fill[w]
            k = rank[w] - below[w]
            if f > cap[w] or k < 1 or k > f:
                out[w] = np.nan
                continue
            o = off[w]
            a = lo[w]
            if not hi[w] > a:  # every value equal
                out[w] = store[o]
                continue
            inv = NARROW_BINS / (hi[w] - a)
            cnt[:] = 0
            for t in range(f):
                cnt[min(np.int64((store[o + t] - a) * inv), NARROW_BINS - 1)] += 1
            before = 0
            kb = 0
            while before + cnt[kb] < k:
                before += cnt[kb]
                kb += 1
            n = 0
            for t in range(f):  # the bin's values to the front, branch-free
                v = store[o + t]
                store[o + n] = v
                n += min(np.int64((v - a) * inv), NARROW_BINS - 1) == kb
            select_inplace(store, o, o + n - 1, o + k - before - 1)
            out[w] = store[o + k - before - 1]


# ---------------------------------------------------------------------------------------------
# Point location by walking from a known simplex to its neighbours.
# ---------------------------------------------------------------------------------------------
#: Barycentric tolerance: a point this close outside a face still counts as inside.
BARY_EPS = 1e-10
#: Longest walk before giving up (only non-Delaunay native meshes can make a walk cycle).
MAX_WALK = 10000
OUTSIDE = -1
WALK_FAILED = -2


@nb.njit(inline="always", **JIT)
def _walk(p, start, transform, neighbors, bary):
    """The walk of `locate`: (simplex or code, last simplex, face left by or -1)."""
    d = p.shape[0]
    s = start
    if s < 0:
        return OUTSIDE, s, -1
    for _ in range(MAX_WALK):
        _bary_in(p, s, transform, bary)
        jmin = 0
        for j in range(1, d + 1):
            if bary[j] < bary[jmin]:
                jmin = j
        if bary[jmin] >= -BARY_EPS:
            return s, s, -1
        nxt = neighbors[s, jmin]
        if nxt < 0:
            return OUTSIDE, s, jmin
        s = nxt
    return WALK_FAILED, s, -1


@nb.njit(**JIT)
def locate(p, start, transform, neighbors, bary):
    """Simplex containing ``p``, walking from ``start`` across the most violated face.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    start : int
        A simplex near ``p`` (the node's own).
    transform : ndarray, shape (m, d + 1, d)
    neighbors : ndarray, shape (m, d + 1)
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates of ``p`` in the returned simplex.

    Returns
    -------
    int
        The simplex, ``OUTSIDE`` (-1) if the walk leaves the mesh, ``WALK_FAILED`` (-2) after
        ``MAX_WALK`` steps. On a non-convex mesh a walk can leave through a border face
        although ``p`` is inside (behind a notch): `locate_exact` settles those, `settle_walk`
        a failed walk.
    """
    return _walk(p, start, transform, neighbors, bary)[0]


#: `face_excess` values up to this (in heights of the cell above the face) count as 0: the face
#: is a supporting plane of the mesh, within the rounding of the barycentric coordinates.
EXCESS_TOL = 1e-9
#: Relative margin on a face excess before a point beyond it is declared outside.
EXCESS_MARGIN = 1e-9


@nb.njit(**JIT)
def find_cell(p, transform, box, dims, bstart, bcells, bary):
    """Simplex containing ``p`` by testing every simplex listed in its bucket (exact search).

    Of the simplices that contain ``p`` (all barycentric coordinates >= -BARY_EPS), the one
    where ``p`` lies deepest (largest smallest coordinate; the first listed on ties): the
    answer does not depend on the order of the list.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    transform : ndarray, shape (m, d + 1, d)
    box : ndarray, shape (2, d)
        Lower corner of the bucket grid (mm) and buckets per mm along each axis.
    dims : ndarray, shape (d,), int64
        Buckets along each axis (C order of the flat bucket index).
    bstart : ndarray, int64; bcells : ndarray, int32
        CSR lists: the simplices whose (padded) bounding box meets bucket b are
        ``bcells[bstart[b]:bstart[b + 1]]`` (`cfm_fem.interpolation.cell_buckets`).
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates in the returned simplex (as `locate` computes them).

    Returns
    -------
    int
        The simplex, or ``OUTSIDE``.
    """
    d = p.shape[0]
    b = 0
    for a in range(d):
        x = (p[a] - box[0, a]) * box[1, a]
        if not (x == x):  # NaN
            return OUTSIDE
        # beyond the grid: its border bucket lists every cell that reaches beyond it
        # (`cfm_fem.interpolation.grid_extent`), or none when the grid covers every cell
        x = min(max(x, 0.0), dims[a] - 0.5)
        b = b * dims[a] + np.int64(x)
    return _deepest(p, transform, bcells, bstart[b], bstart[b + 1], bary)


@nb.njit(inline="always", **JIT)
def _deepest(p, transform, cells, lo, hi, bary):
    """The simplex holding ``p`` deepest (largest smallest barycentric coordinate) among
    ``cells[lo:hi]``, or among simplices ``lo .. hi - 1`` when ``cells`` is empty; ``OUTSIDE``
    if none holds it. ``bary``: its barycentric coordinates (as `locate` computes them)."""
    best = OUTSIDE
    best_min = 0.0
    for i in range(lo, hi):
        s = np.int64(cells[i]) if cells.shape[0] > 0 else np.int64(i)
        lmin = _depth(p, s, transform)
        if lmin >= -BARY_EPS and (best < 0 or lmin > best_min):
            best = s
            best_min = lmin
    if best >= 0:
        _bary_in(p, best, transform, bary)
    return best


@nb.njit(inline="always", **JIT)
def _depth(p, s, transform):
    """Smallest barycentric coordinate of ``p`` in simplex ``s`` (>= -BARY_EPS: inside)."""
    d = p.shape[0]
    last = 1.0
    lmin = np.inf
    for j in range(d):
        c = 0.0
        for k in range(d):
            c += transform[s, j, k] * (p[k] - transform[s, d, k])
        last -= c
        lmin = min(lmin, c)
    return min(lmin, last)


@nb.njit(**JIT)
def settle_walk(p, transform, search, bary):
    """Simplex containing ``p`` for a walk that failed (`WALK_FAILED`), found exactly.

    Only a walk that cycles runs out of its ``MAX_WALK`` steps: not on a Delaunay or grid
    mesh (in exact arithmetic the walk is acyclic there), rarely if ever on a native one (none in
    2,000 random non-Delaunay 2-D and 400 3-D meshes tried). Counting its trial as lost took
    the node's U_f away. With search arrays (a non-convex mesh) the bucket search `find_cell`
    answers. Without (a convex mesh: `cfm_fem.interpolation.no_search`) every simplex is
    tested: O(m), about 2 ms per 1e5 cells, paid only for a failed walk.

    Parameters
    ----------
    p, transform, bary :
        As in `locate`.
    search : tuple
        As in `locate_exact`.

    Returns
    -------
    int
        The simplex where ``p`` lies deepest (as `find_cell`), or ``OUTSIDE`` (in none).

    Notes
    -----
    The out-of-core sweep (`cfm_fem.slabs`) appends a sentinel cell and copies of
    uncertified cells to its arrays, which this search does not tell from the mesh; its meshes
    are Delaunay or Kuhn grids, whose walks do not cycle: it does not come here.
    """
    excess, _reach, box, dims, bstart, bcells = search
    if excess.shape[0] > 0:
        return find_cell(p, transform, box, dims, bstart, bcells, bary)
    return _deepest(p, transform, bcells[:0], 0, transform.shape[0], bary)  # every simplex


@nb.njit(inline="always", **JIT)
def _bary_in(p, s, transform, bary):
    """Barycentric coordinates of p in simplex s, as `locate` computes them."""
    d = p.shape[0]
    last = 1.0
    for j in range(d):
        c = 0.0
        for k in range(d):
            c += transform[s, j, k] * (p[k] - transform[s, d, k])
        bary[j] = c
        last -= c
    bary[d] = last


@nb.njit(**JIT)
def locate_exact(p, start, transform, neighbors, bary, search):
    """`locate`, exact on non-convex meshes too.

    A walk that leaves the mesh through a border face proves ``p`` outside only when ``p`` lies
    beyond that face's plane by more than any node of the mesh does (its `face_excess`): then
    no cell can hold it. Otherwise (behind a notch, or a face left by removed hull slivers) the
    cells of ``p``'s bucket are tested (`find_cell`). On a convex mesh (empty excess table)
    this is `locate`, step for step. A ``WALK_FAILED`` is returned as is, for the caller to
    settle with `settle_walk` (that call made here took about 20 % more CPU time for the whole
    Gaussian sweep, though never run).

    Parameters
    ----------
    p, start, transform, neighbors, bary :
        As in `locate`.
    search : tuple
        ``(excess, reach, box, dims, bstart, bcells)`` (`cfm_fem.interpolation.exact_search`):
        excess, shape (m, d + 1) or (0, d + 1), the `face_excess` of each border face in
        heights of its cell (0 elsewhere); reach, shape (n,) or (0,), `node_reach` (mm); the
        rest, the bucket lists of `find_cell`.

    Returns
    -------
    int
        As `locate`.
    """
    excess, _reach, box, dims, bstart, bcells = search
    s, last, face = _walk(p, start, transform, neighbors, bary)
    if s != OUTSIDE or face < 0 or excess.shape[0] == 0:
        return s
    if -bary[face] > excess[last, face] * (1.0 + EXCESS_MARGIN) + BARY_EPS:
        return OUTSIDE  # beyond the plane by more than every node of the mesh
    return find_cell(p, transform, box, dims, bstart, bcells, bary)


@nb.njit(**JIT)
def node_reach(coords, simplices, transform, boxes, box, dims, bstart, bcells, nodes, cap):
    """Per node g, a distance within which the only cells are g's own (its star).

    A lower bound on the distance from g to the cells not incident to g: per cell, the larger
    of the distance to its bounding box and the largest distance of g beyond one of its face
    planes (``-lam_j(g) / |grad lam_j|``), the least over the cells whose bounding box comes
    within ``cap`` of g (the others are farther than that). A point nearer to g than this is
    in the mesh if and only if it is in a star cell, however the mesh folds further away:
    `star_exit` proves trials outside with it.

    The least is found without testing every cell within ``cap``: the cells of g's own bucket
    first, then only the buckets within the distance found so far (a cell whose box is that
    near is listed in one of them), each cell once (at the first of those buckets that lists
    it) and only while its box is nearer than the distance found so far. The cells left out
    cannot lower it, so the result is that of testing them all, bit for bit (a least over a
    set does not depend on the order).

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices, transform : mesh arrays
    boxes : ndarray, shape (m, 2, d), mm
        Lower and upper corner of each cell's bounding box (`cell_boxes`).
    box, dims, bstart, bcells : bucket lists of the cells (`find_cell`), built from ``boxes``
        (`bucket_lists`)
    nodes : ndarray, shape (k,), int64
    cap : ndarray, shape (k,), mm
        Search radius per node (`star_sizes`).

    Returns
    -------
    ndarray, shape (k,), mm
        At most ``cap``; 0 where a cell not incident to g touches it (a non-conforming mesh).
    """
    d = coords.shape[1]
    out = np.empty(nodes.shape[0])
    lo = np.empty(d, dtype=np.int64)
    hi = np.empty(d, dtype=np.int64)
    own = np.empty(d, dtype=np.int64)
    c0 = np.empty(d, dtype=np.int64)
    c1 = np.empty(d, dtype=np.int64)
    gsum = np.empty(d)
    # a margin on the radius of the second pass, far above the rounding of the bucket indices
    margin = np.inf
    for a in range(d):
        margin = min(margin, 1e-6 / box[1, a])
    e = 3 - d
    n1 = dims[1 - e]
    n2 = dims[2 - e]
    idx = np.empty(d, dtype=np.int64)  # the bucket's index along each axis
    for i in range(nodes.shape[0]):
        g = nodes[i]
        r = cap[i]
        if not _reach_range(coords, g, r, box, dims, lo, hi):
            out[i] = r
            continue
        # pass 1: g's own bucket (inside the range of cap, as the index is monotonic)
        b_own = 0
        for a in range(d):
            x = np.floor((coords[g, a] - box[0, a]) * box[1, a])
            own[a] = min(max(np.int64(max(x, -1.0)), lo[a]), hi[a])
            b_own = b_own * dims[a] + own[a]
        for k in range(bstart[b_own], bstart[b_own + 1]):
            c = bcells[k]
            gap = _box_gap(coords, g, boxes, c)
            r = _reach_cell(coords, simplices, transform, g, c, gap, cap[i], r, gsum)
        # pass 2: the other buckets within r (narrowed range of cap), each cell once; three
        # nested loops as in `_bucket_pass`
        _reach_range(coords, g, min(r + margin, cap[i]), box, dims, lo, hi)
        x0 = lo[0] if e == 0 else 0
        x1 = hi[0] if e == 0 else 0
        for x in range(x0, x1 + 1):
            if e == 0:
                idx[0] = x
            for y in range(lo[1 - e], hi[1 - e] + 1):
                idx[1 - e] = y
                row = (x * n1 + y) * n2
                for z in range(lo[2 - e], hi[2 - e] + 1):
                    idx[2 - e] = z
                    b = row + z
                    if b == b_own:
                        continue
                    for k in range(bstart[b], bstart[b + 1]):
                        c = bcells[k]
                        gap = _box_gap(coords, g, boxes, c)
                        if gap > cap[i] * cap[i] or math.sqrt(gap) >= r:
                            continue  # as `_reach_cell` would: r stays
                        _padded_range(boxes, c, box, dims, c0, c1)
                        first = True  # b is the first bucket of the range that lists c
                        for a in range(d):
                            first &= max(c0[a], lo[a]) == idx[a]
                        if first:
                            r = _reach_cell(coords, simplices, transform, g, c, gap, cap[i], r,
                                            gsum)  # fmt: skip
        out[i] = r
    return out


@nb.njit(inline="always", **JIT)
def _reach_range(coords, g, r, box, dims, lo, hi):
    """Buckets within ``r`` of node g along each axis (lo..hi, clipped); False: none."""
    d = coords.shape[1]
    for a in range(d):
        x0 = np.floor((coords[g, a] - r - box[0, a]) * box[1, a])
        x1 = np.floor((coords[g, a] + r - box[0, a]) * box[1, a])
        lo[a] = np.int64(max(x0, 0.0))
        hi[a] = np.int64(min(x1, dims[a] - 1.0))
        if hi[a] < lo[a]:
            return False
    return True


@nb.njit(inline="always", **JIT)
def _box_gap(coords, g, boxes, c):
    """Squared distance from node g to cell c's bounding box, mm^2."""
    gap = 0.0
    for a in range(coords.shape[1]):
        x = coords[g, a]
        gap += max(boxes[c, 0, a] - x, 0.0, x - boxes[c, 1, a]) ** 2
    return gap


@nb.njit(inline="always", **JIT)
def _reach_cell(coords, simplices, transform, g, c, gap, cap, r, gsum):
    """`node_reach`'s distance r after cell c (squared distance ``gap`` from g to its box):
    min(r, its bound) if c is not g's and its box is within ``cap`` of g; r unchanged when the
    box is not nearer than r (no bound can be)."""
    d = coords.shape[1]
    if gap > cap * cap:
        return r
    dist = math.sqrt(gap)
    if dist >= r:
        return r
    for j in range(d + 1):
        if simplices[c, j] == g:
            return r
    lb = 0.0
    lsum = 0.0
    for a in range(d):
        gsum[a] = 0.0
    for j in range(d):
        lam = 0.0
        gn = 0.0
        for a in range(d):
            lam += transform[c, j, a] * (coords[g, a] - transform[c, d, a])
            gn += transform[c, j, a] ** 2
            gsum[a] += transform[c, j, a]
        lsum += lam
        if lam < 0.0:
            lb = max(lb, -lam / math.sqrt(gn))
    gn = 0.0
    for a in range(d):
        gn += gsum[a] ** 2
    if 1.0 - lsum < 0.0:
        lb = max(lb, -(1.0 - lsum) / math.sqrt(gn))
    return min(r, max(lb, dist))  # both bound the distance from below


@nb.njit(**JIT)
def cell_boxes(coords, simplices):
    """Bounding box of each cell.

    Parameters
    ----------
    coords : ndarray, shape (n, d), mm
    simplices : ndarray, shape (m, d + 1), int

    Returns
    -------
    ndarray, shape (m, 2, d), mm
        Lower and upper corner: the least and the largest coordinate of the cell's vertices.
    """
    m, dp1 = simplices.shape
    d = coords.shape[1]
    out = np.empty((m, 2, d))
    for c in range(m):
        for a in range(d):
            lo = coords[simplices[c, 0], a]
            hi = lo
            for j in range(1, dp1):
                x = coords[simplices[c, j], a]
                lo = min(lo, x)
                hi = max(hi, x)
            out[c, 0, a] = lo
            out[c, 1, a] = hi
    return out


@nb.njit(inline="always", **JIT)
def _padded(boxes, c):
    """The padding of cell c's box in the bucket grid: 1e-8 of its largest side, so a point
    the cell holds within the barycentric tolerance is inside the padded box."""
    side = 0.0
    for a in range(boxes.shape[2]):
        side = max(side, boxes[c, 1, a] - boxes[c, 0, a])
    return 1e-8 * side


@nb.njit(**JIT)
def padded_extent(boxes):
    """Lower and upper corner of the union of the padded cell boxes (`_padded`), mm, shape
    (2, d): the extent of the bucket grid (`cfm_fem.interpolation.cell_buckets`)."""
    m, _, d = boxes.shape
    out = np.empty((2, d))
    out[0] = np.inf
    out[1] = -np.inf
    for c in range(m):
        pad = _padded(boxes, c)
        for a in range(d):
            out[0, a] = min(out[0, a], boxes[c, 0, a] - pad)
            out[1, a] = max(out[1, a], boxes[c, 1, a] + pad)
    return out


@nb.njit(inline="always", **JIT)
def _padded_range(boxes, c, box, dims, i0, i1):
    """First and last bucket along each axis (clipped to the grid) that cell c's padded box
    meets, into i0, i1."""
    pad = _padded(boxes, c)
    for a in range(boxes.shape[2]):
        x0 = np.int64(np.floor((boxes[c, 0, a] - pad - box[0, a]) * box[1, a]))
        x1 = np.int64(np.floor((boxes[c, 1, a] + pad - box[0, a]) * box[1, a]))
        i0[a] = min(max(x0, 0), dims[a] - 1)
        i1[a] = min(max(x1, 0), dims[a] - 1)


@nb.njit(**JIT)
def bucket_entries(boxes, box, dims):
    """How many (cell, bucket) entries the lists of `bucket_lists` would hold."""
    d = boxes.shape[2]
    i0 = np.empty(d, dtype=np.int64)
    i1 = np.empty(d, dtype=np.int64)
    total = 0
    for c in range(boxes.shape[0]):
        _padded_range(boxes, c, box, dims, i0, i1)
        n = 1
        for a in range(d):
            n *= i1[a] - i0[a] + 1
        total += n
    return total


@nb.njit(inline="always", **JIT)
def _bucket_pass(boxes, box, dims, slot, out):
    """One pass of `bucket_lists`: with ``out`` empty, count the cells of each bucket into
    ``slot[b + 1]``; else write each cell at ``slot[b]`` of its buckets and advance it."""
    m, _, d = boxes.shape
    i0 = np.empty(d, dtype=np.int64)
    i1 = np.empty(d, dtype=np.int64)
    # three nested loops (a planar mesh: one bucket along a first axis of its own), twice as
    # fast as a loop over d axes
    e = 3 - d
    n1 = dims[1 - e]
    n2 = dims[2 - e]
    count = out.shape[0] == 0
    for c in range(m):
        _padded_range(boxes, c, box, dims, i0, i1)
        x0 = i0[0] if e == 0 else 0
        x1 = i1[0] if e == 0 else 0
        for x in range(x0, x1 + 1):
            for y in range(i0[1 - e], i1[1 - e] + 1):
                row = (x * n1 + y) * n2
                for b in range(row + i0[2 - e], row + i1[2 - e] + 1):  # last axis fastest
                    if count:
                        slot[b + 1] += 1
                    else:
                        out[slot[b]] = c
                        slot[b] += 1


@nb.njit(**JIT)
def bucket_lists(boxes, box, dims):
    """CSR lists of the buckets each cell's padded box meets
    (`cfm_fem.interpolation.cell_buckets`), counted, then filled in cell order: no
    temporaries per entry or per cell.

    Parameters
    ----------
    boxes : ndarray, shape (m, 2, d), mm
        The cells' bounding boxes (`cell_boxes`), padded here (`_padded`).
    box : ndarray, shape (2, d)
        Lower corner of the grid (mm) and buckets per mm along each axis.
    dims : ndarray, shape (d,), int64
        Buckets along each axis; flat bucket index in C order.

    Returns
    -------
    bstart : ndarray, shape (prod(dims) + 1,), int64
    bcells : ndarray, int32
        The cells meeting bucket b, increasing: ``bcells[bstart[b]:bstart[b + 1]]``.
    """
    n_b = 1
    for a in range(dims.shape[0]):
        n_b *= dims[a]
    bstart = np.zeros(n_b + 1, dtype=np.int64)
    _bucket_pass(boxes, box, dims, bstart, np.empty(0, dtype=np.int32))
    for b in range(n_b):
        bstart[b + 1] += bstart[b]
    fill = bstart[:-1].copy()
    bcells = np.empty(bstart[n_b], dtype=np.int32)  # held for the run: 4 bytes per entry
    _bucket_pass(boxes, box, dims, fill, bcells)
    return bstart, bcells


@nb.njit(**JIT)
def star_sizes(nodes, start, simplices, neighbors, transform):
    """Per node g, the cells reached from ``start[g]`` across faces that contain g (its star,
    as `build_star` builds it), counted up to MAX_STAR + 1, and g's largest height over the
    face opposite it in one of them.

    Fewer than the cells incident to g: the node's cells form several face-connected parts
    (a node where removed hull slivers or a pinched mesh leave two wedges meeting at an edge or
    a point); the star then misses incident cells, and `node_reach` is no proof there.
    Otherwise the height is over all of g's cells: `node_reach`'s search radius (the cells
    across those faces are about that near, so a wider search would seldom find a larger
    reach).

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
    start : ndarray, shape (n,), int64
        A cell incident to each node (-1: none).
    simplices, neighbors : ndarray, shape (m, d + 1), int64
    transform : ndarray, shape (m, d + 1, d)

    Returns
    -------
    sizes : ndarray, shape (k,), int64
    height : ndarray, shape (k,), mm
        1 / |grad lam_j| of the cells s counted, j the vertex of s at g, largest (0 for a node
        in no cell).
    """
    dp1 = simplices.shape[1]
    out = np.zeros(nodes.shape[0], dtype=np.int64)
    height = np.zeros(nodes.shape[0])
    seen = np.empty(MAX_STAR + 1, dtype=np.int64)
    for i in range(nodes.shape[0]):
        g = nodes[i]
        if start[g] < 0:
            continue
        seen[0] = start[g]
        n = 1
        k = 0
        while k < n:  # breadth-first across the faces that contain g
            s = seen[k]
            k += 1
            for j in range(dp1):
                ns = neighbors[s, j]
                if simplices[s, j] == g:
                    height[i] = max(height[i], _node_height(transform, s, j))
                if simplices[s, j] == g or ns < 0:
                    continue
                new = True
                for q in range(n):
                    new &= seen[q] != ns
                if new and n <= MAX_STAR:
                    seen[n] = ns
                    n += 1
        out[i] = n
    return out, height


@nb.njit(inline="always", **JIT)
def _node_height(transform, s, j):
    """Height of vertex j of cell s over the opposite face, 1 / |grad lam_j|, mm (the gradient
    of the last coordinate is minus the sum of the others, summed in numpy's order)."""
    d = transform.shape[2]
    gn = 0.0
    for a in range(d):
        if j < d:
            v = transform[s, j, a]
        else:
            v = transform[s, 0, a]
            for q in range(1, d):
                v += transform[s, q, a]
        gn += v * v
    return 1.0 / math.sqrt(gn)


@nb.njit(**JIT)
def hull_max(points, adj_start, adj, start, grad, shift):
    """max over the vertices v of a convex hull of ``grad[f] . points[v] + shift[f]``, per f.

    Climbs the hull's edge graph from ``start[f]`` to a neighbour with a larger value while
    there is one: on a convex polytope a vertex no edge improves is a maximum (the simplex
    method's argument), so the answer is the brute-force maximum over all vertices
    (`cfm_fem.interpolation.face_excess`: tens of steps per face instead of every vertex).

    Parameters
    ----------
    points : ndarray, shape (h, d), mm
        The hull's vertices.
    adj_start, adj : ndarray, int64
        CSR lists of the hull's edges: the neighbours of vertex v are
        ``adj[adj_start[v]:adj_start[v + 1]]``.
    start : ndarray, shape (f,), int64
        Vertex to climb from (one near the maximum saves steps).
    grad : ndarray, shape (f, d); shift : ndarray, shape (f,)

    Returns
    -------
    ndarray, shape (f,)
    """
    nf, d = grad.shape
    out = np.empty(nf)
    for f in range(nf):
        v = start[f]
        best = shift[f]
        for a in range(d):
            best += grad[f, a] * points[v, a]
        while True:
            nxt = -1
            for i in range(adj_start[v], adj_start[v + 1]):
                w = adj[i]
                val = shift[f]
                for a in range(d):
                    val += grad[f, a] * points[w, a]
                if val > best:
                    best = val
                    nxt = w
            if nxt < 0:
                break
            v = nxt
        out[f] = best
    return out


@nb.njit(inline="always", **JIT)
def _walk_step3(p0, p1, p2, s, transform):
    """One step of the d = 3 walk in simplex ``s``: the barycentric coordinates of p, the face
    to cross (the first most negative coordinate, chosen by selects: at every step its outcome
    is a coin toss, so a branch would mispredict) and whether p is inside."""
    x0 = p0 - transform[s, 3, 0]
    x1 = p1 - transform[s, 3, 1]
    x2 = p2 - transform[s, 3, 2]
    b0 = 0.0 + transform[s, 0, 0] * x0 + transform[s, 0, 1] * x1 + transform[s, 0, 2] * x2
    b1 = 0.0 + transform[s, 1, 0] * x0 + transform[s, 1, 1] * x1 + transform[s, 1, 2] * x2
    b2 = 0.0 + transform[s, 2, 0] * x0 + transform[s, 2, 1] * x1 + transform[s, 2, 2] * x2
    b3 = 1.0 - b0 - b1 - b2
    m01 = min(b0, b1)
    m23 = min(b2, b3)
    j01 = np.uint64(1) if b1 < b0 else np.uint64(0)
    j23 = np.uint64(3) if b3 < b2 else np.uint64(2)
    jmin = j23 if m23 < m01 else j01
    return b0, b1, b2, b3, jmin, min(m01, m23) >= -BARY_EPS


@nb.njit(inline="always", **JIT)
def _interp_in(s, bary, simplices, values, out):
    """out = sum_j bary[j] * values[simplices[s, j]]."""
    for c in range(out.shape[0]):
        out[c] = 0.0
    for j in range(simplices.shape[1]):
        w = bary[j]
        v = simplices[s, j]
        for c in range(out.shape[0]):
            out[c] += w * values[v, c]


#: Points per block of the batched walk: its work space stays in the L1/L2 cache.
WALK_BLOCK = 1024


@nb.njit(**JIT)
def walk_block3(points, i0, n, start, transform, neighbors, cur, act, bary):
    """`locate` of points ``i0 .. i0 + n - 1`` (d = 3), one step of every unfinished walk per round.

    Each round tests the current cell of every walk still going, in a loop without branches
    that depend on the data: a point-by-point walk ends with a mispredicted branch at a
    random step, and the CPU throws away the work it had in flight for the next points. Same
    cells, same sums and the same face crossed at every step as `locate`, so the same results.

    Parameters
    ----------
    points : ndarray, shape (k, 3), mm
    i0, n : int
        The block: points i0 .. i0 + n - 1, n <= len(cur).
    start : ndarray, shape (>= n,), int64
        Starting simplex of the walk of point i0 + j at j.
    cur : ndarray, shape (>= n,), int64
        Output: containing simplex of point i0 + j, or ``OUTSIDE`` / ``WALK_FAILED``.
    act : ndarray, shape (>= n,), int64
        Work space.
    bary : ndarray, shape (>= n, 4)
        Output: barycentric coordinates in ``cur[j]`` (meaningful where cur[j] >= 0).
    """
    m = 0
    for j in range(n):
        s = start[j]
        cur[j] = s if s >= 0 else OUTSIDE
        act[m] = j
        m += s >= 0
    for _ in range(MAX_WALK):
        if m == 0:
            return
        m_next = 0
        for t in range(m):
            j = act[t]
            i = i0 + j
            s = np.uint64(cur[j])  # unsigned: no wrap-around code for the gathers
            b0, b1, b2, b3, jmin, inside = _walk_step3(
                points[i, 0], points[i, 1], points[i, 2], s, transform
            )
            bary[j, 0] = b0
            bary[j, 1] = b1
            bary[j, 2] = b2
            bary[j, 3] = b3
            nxt = neighbors[s, jmin]  # OUTSIDE when the walk leaves the mesh
            # the cell a walk goes on with, by arithmetic: LLVM turns a select here into a
            # branch, whose outcome (inside or not) is a coin toss (a two-slot array, as before,
            # was 4-6 % slower)
            ins = np.int64(inside)
            cur[j] = nxt + (np.int64(s) - nxt) * ins
            act[m_next] = j  # branch-free compaction of the walks still going
            m_next += (1 - ins) & np.int64(nxt >= 0)
        m = m_next
    for t in range(m):
        cur[act[t]] = WALK_FAILED


@nb.njit(**PJIT)
def interpolate_points(points, start, simplices, transform, neighbors, values, out, cell):
    """Piecewise-linear values at ``points``; NaN where outside the mesh.

    In 3-D the walks of a block of points advance together (`walk_block3`); in other
    dimensions each point walks on its own (`locate`). Both give the same cells and values.

    Parameters
    ----------
    points : ndarray, shape (k, d), mm, in the mesh frame
    start : ndarray, shape (k,), int64
        Starting simplex of each walk (e.g. the simplex of the nearest node, or its
        `octant_cells` entry for the point's side, which saves most of the steps).
    values : ndarray, shape (n, c)
    out : ndarray, shape (k, c)
        Output: the values.
    cell : ndarray, shape (k,), int64
        Output: containing simplex, or -1 (outside) / -2 (walk failed).

    Notes
    -----
    The caller allocates the outputs (`cfm_fem.interpolation.interpolate_points`): numpy asks
    for transparent huge pages for large arrays, so their first touch costs fewer page faults
    (here, 5e6 points: 0.02-0.03 s instead of 0.04 s, within the noise of a whole call).
    """
    k = points.shape[0]
    d = points.shape[1]
    nc = values.shape[1]
    block = WALK_BLOCK  # work space once per block of points, not per point
    for b in nb.prange((k + block - 1) // block):
        i0 = b * block
        n = min(block, k - i0)
        cur = np.empty(block, dtype=np.int64)
        bary = np.empty((block, d + 1))
        if d == 3:
            act = np.empty(block, dtype=np.int64)
            walk_block3(points, i0, n, start[i0 : i0 + n], transform, neighbors, cur, act, bary)
            # `_interp_in` written out for four vertices, without array views per point: 37 ->
            # 23 ns per point of one-step walks (the same sums in the same order)
            for j in range(n):
                s = cur[j]
                i = i0 + j
                cell[i] = s
                if s >= 0:
                    v0, v1 = simplices[s, 0], simplices[s, 1]
                    v2, v3 = simplices[s, 2], simplices[s, 3]
                    w0, w1, w2, w3 = bary[j, 0], bary[j, 1], bary[j, 2], bary[j, 3]
                    for c in range(nc):
                        out[i, c] = (
                            0.0 + w0 * values[v0, c] + w1 * values[v1, c] + w2 * values[v2, c]
                        ) + w3 * values[v3, c]
                else:
                    for c in range(nc):
                        out[i, c] = np.nan
        else:
            for j in range(n):
                cur[j] = locate(points[i0 + j], start[i0 + j], transform, neighbors, bary[j])
            for j in range(n):
                s = cur[j]
                cell[i0 + j] = s
                if s >= 0:
                    _interp_in(s, bary[j], simplices, values, out[i0 + j])
                else:
                    for c in range(nc):
                        out[i0 + j, c] = np.nan


def octant_cells(coords, node_cell, transform, neighbors, eps):
    """Per node, the simplex that contains node + eps * (+-1, +-1[, +-1]) for each sign pattern.

    A walk for a displacement starts from the cell of its octant (bit a of the index set when
    component a is negative, as in `octant_starts`), which cuts the walk across the node's star
    to about one step. In 3-D the eight walks of a block of nodes advance together
    (`walk_block3`). Blocks of nodes run on numba's number of threads (`cfm_fem.threads`): a
    numba parallel loop would compile the walk kernels once more on first use (~1 s).

    Returns
    -------
    ndarray, shape (n, 2**d), int64
        Start simplex per node and octant (the node's own cell where the probe leaves the mesh).
    """

    def work(g0, g1):
        return (_octant_rows(coords, node_cell, transform, neighbors, eps, g0, g1),)

    return map_blocks(work, len(coords), 2048)[0]


@nb.njit(**JIT)
def _octant_rows(coords, node_cell, transform, neighbors, eps, n0, n1):
    """Rows n0 .. n1-1 of `octant_cells`."""
    d = coords.shape[1]
    n_oct = 1 << d
    out = np.empty((n1 - n0, n_oct), dtype=np.int64)
    per = WALK_BLOCK // n_oct  # nodes per block
    for b in range((n1 - n0 + per - 1) // per):
        g0 = n0 + b * per
        g1 = min(n1, g0 + per)
        m = (g1 - g0) * n_oct
        p = np.empty((m, d))
        st = np.empty(m, dtype=np.int64)
        for g in range(g0, g1):
            for o in range(n_oct):
                r = (g - g0) * n_oct + o
                st[r] = node_cell[g]
                for a in range(d):
                    p[r, a] = coords[g, a] + (-eps if (o >> a) & 1 else eps)
        found = np.empty(m, dtype=np.int64)
        if d == 3:
            act = np.empty(m, dtype=np.int64)
            bary = np.empty((m, 4))
            walk_block3(p, 0, m, st, transform, neighbors, found, act, bary)
        else:
            bary1 = np.empty(d + 1)
            for r in range(m):
                found[r] = locate(p[r], st[r], transform, neighbors, bary1)
        for g in range(g0, g1):
            for o in range(n_oct):
                s = found[(g - g0) * n_oct + o]
                out[g - n0, o] = s if s >= 0 else node_cell[g]
    return out


@nb.njit(**PJIT)
def octant_starts(points, node, coords, start_cells):
    """Walk start of each point from the `octant_cells` row of the node it was drawn around.

    Parameters
    ----------
    points : ndarray, shape (k, d), mm
    node : ndarray, shape (k,), int64
        The node each point is a perturbation of.
    coords : ndarray, shape (n, d), mm
    start_cells : ndarray, shape (n, 2**d), int64

    Returns
    -------
    ndarray, shape (k,), int64
        ``start_cells[node, octant]``, bit a of the octant set where the point is below the
        node in coordinate a.
    """
    k, d = points.shape
    out = np.empty(k, dtype=np.int64)
    for i in nb.prange(k):
        g = node[i]
        o = 0
        for a in range(d):
            o |= np.int64(points[i, a] < coords[g, a]) << a
        out[i] = start_cells[g, o]
    return out


# -- interpolation of points grouped around nodes (the perturbation sweep's access pattern) ----

#: Most cells in a node's star that `interpolate_groups` handles with its vectorised cone test
#: (their index goes into the low bits of a float); a larger star (a degenerate fan) walks.
STAR_MAX_CELLS = 256
_STAR_TAG = np.uint64(STAR_MAX_CELLS - 1)


@intrinsic
def _bits_from_float(typingctx, x):
    """The IEEE-754 bits of ``x``: a float64 as a uint64, a float32 as a uint32 (a cast that
    vectorises)."""
    if x not in (types.float64, types.float32):
        return None
    width = x.bitwidth

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(width))

    return getattr(types, f"uint{width}")(x), codegen


@intrinsic
def _with_bits(typingctx, like, bits):
    """The float of ``like``'s type whose IEEE-754 bits are the low bits of the integer
    ``bits`` (a cast that vectorises)."""
    if like not in (types.float64, types.float32) or not isinstance(bits, types.Integer):
        return None
    width = like.bitwidth

    def codegen(context, builder, signature, args):
        b = args[1]
        if bits.bitwidth > width:
            b = builder.trunc(b, ir.IntType(width))
        elif bits.bitwidth < width:
            b = builder.zext(b, ir.IntType(width))
        return builder.bitcast(b, context.get_value_type(like))

    return like(like, bits), codegen


@intrinsic
def _prefetch(typingctx, arr, offset):
    """Ask the CPU to start loading the cache line of element ``offset`` (flat index, C order)
    of the contiguous array ``arr``. A hint: it changes no result."""
    if not isinstance(arr, types.Array) or not isinstance(offset, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        off = context.cast(builder, args[1], signature.args[1], types.intp)
        i8p = builder.bitcast(builder.gep(ary.data, [off]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p.type, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p.type], fnty)
        builder.call(fn, [i8p, i32(0), i32(3), i32(1)])  # read, keep in all cache levels, data
        return context.get_dummy_value()

    return types.void(arr, offset), codegen


@nb.njit(**JIT)
def node_cells(simplices, n_nodes):
    """The cells around each node (its star), as compressed rows.

    Parameters
    ----------
    simplices : ndarray, shape (m, d + 1), int64
    n_nodes : int

    Returns
    -------
    start : ndarray, shape (n_nodes + 1,), int64
    cells : ndarray, shape (m * (d + 1),), int32
        The cells holding node g are ``cells[start[g]:start[g + 1]]``, in increasing order.
    """
    m, k = simplices.shape
    start = np.zeros(n_nodes + 1, dtype=np.int64)
    for s in range(m):
        for j in range(k):
            start[simplices[s, j] + 1] += 1
    for g in range(n_nodes):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    cells = np.empty(m * k, dtype=np.int32)
    for s in range(m):
        for j in range(k):
            v = simplices[s, j]
            cells[fill[v]] = s
            fill[v] += 1
    return start, cells


@nb.njit(inline="always", **JIT)
def _place_in_cell(simplices, s, g):
    """The place (0 .. 3) of node g among the vertices of tetrahedron s, without branches."""
    return (
        np.int64(simplices[s, 1] == g)
        + 2 * np.int64(simplices[s, 2] == g)
        + 3 * np.int64(simplices[s, 3] == g)
    )


#: Bound on |cone test in float32 - in float64| / (max |cone entry| * sum |d_a|): the
#: rounding of d and of the cone rows to float32 and of three products summed, 5 * 2**-24,
#: with a margin of 3.
_CONE32_TOL = 1e-6


@nb.njit(**FJIT)
def _cone_tables(g, c0, ns, star, simplices, transform, values, cone, cone32, grad, far):
    """Per cell k of node g's star: ``cone[k]`` (9) the gradients of the barycentric coordinates
    of its three other vertices (their values at g + d are cone @ d, so d is in the cell's cone
    when all three are >= 0), ``cone32[k]`` the same in float32, ``far[k]`` (3) the gradient
    of g's own (g + d stays on g's side of the opposite face while 1 + far @ d >= 0) and
    ``grad[k]`` (3 per value column) the gradient of the linear interpolant in the cell.

    Returns the tolerance of the float32 cone test per unit of |d|_1 (`_CONE32_TOL` times the
    largest cone entry) and the squared distance, less 1 %, within which no displacement
    reaches a far face (0.99 / max |far|^2), both float32.
    """
    nc = values.shape[1]
    amax = 0.0
    fmax = 0.0
    for k in range(ns):
        s = np.int64(star[c0 + k])
        j = _place_in_cell(simplices, s, g)
        # rows 0-2: grad(lambda_0..2) from the transform; row 3 = -(their sum). The three
        # rows other than g's, and g's, picked with selects (no indexed work array).
        a0, a1, a2 = transform[s, 0, 0], transform[s, 0, 1], transform[s, 0, 2]
        b0, b1, b2 = transform[s, 1, 0], transform[s, 1, 1], transform[s, 1, 2]
        d0, d1, d2 = transform[s, 2, 0], transform[s, 2, 1], transform[s, 2, 2]
        h0, h1, h2 = -(a0 + b0 + d0), -(a1 + b1 + d1), -(a2 + b2 + d2)
        first = j == 0
        second = j <= 1
        third = j <= 2
        row = (
            b0 if first else a0, b1 if first else a1, b2 if first else a2,
            d0 if second else b0, d1 if second else b1, d2 if second else b2,
            h0 if third else d0, h1 if third else d1, h2 if third else d2,
        )  # fmt: skip
        for i in range(9):
            cone[k, i] = row[i]
            cone32[k, i] = np.float32(row[i])
            amax = max(amax, abs(row[i]))
        f0 = a0 if j == 0 else (b0 if j == 1 else (d0 if j == 2 else h0))
        f1 = a1 if j == 0 else (b1 if j == 1 else (d1 if j == 2 else h1))
        f2 = a2 if j == 0 else (b2 if j == 1 else (d2 if j == 2 else h2))
        far[k, 0] = f0
        far[k, 1] = f1
        far[k, 2] = f2
        fmax = max(fmax, f0 * f0 + f1 * f1 + f2 * f2)
        v0, v1, v2, v3 = simplices[s, 0], simplices[s, 1], simplices[s, 2], simplices[s, 3]
        for c in range(nc):
            w3 = values[v3, c]
            e0 = values[v0, c] - w3
            e1 = values[v1, c] - w3
            e2 = values[v2, c] - w3
            grad[k, 3 * c] = e0 * a0 + e1 * b0 + e2 * d0
            grad[k, 3 * c + 1] = e0 * a1 + e1 * b1 + e2 * d1
            grad[k, 3 * c + 2] = e0 * a2 + e1 * b2 + e2 * d2
    return np.float32(_CONE32_TOL * amax), np.float32(0.99 / fmax)


@nb.njit(inline="always", **FJIT)
def _tagged_min(c, k, x, y, z):
    """min of the three cone coordinates (``c``: the 9 numbers of `_cone_tables`' cone row)
    of displacement (x, y, z) in star cell k, its low 8 bits replaced by k: the max over the
    cells of these is the cell where the point lies deepest, tagged, in one float (of the
    type of x: in float32 the tag moves the value by at most 2**-15 of itself, never its
    sign)."""
    l0 = c[0] * x + c[1] * y + c[2] * z
    l1 = c[3] * x + c[4] * y + c[5] * z
    l2 = c[6] * x + c[7] * y + c[8] * z
    m = min(min(l0, l1), l2)
    return _with_bits(m, (_bits_from_float(m) & ~_STAR_TAG) | np.uint64(k))


@nb.njit(inline="always", **JIT)
def _cone_row(cone, k):
    """Row k of the cone table as a tuple: scalars the vectorised loops keep in registers (a
    table read inside them would be read again for every point, as it might alias the
    stores)."""
    return (cone[k, 0], cone[k, 1], cone[k, 2], cone[k, 3], cone[k, 4], cone[k, 5],
            cone[k, 6], cone[k, 7], cone[k, 8])  # fmt: skip


@nb.njit(inline="always", **JIT)
def _tag_cell(tagged, ns):
    """The star cell whose index `_tagged_min` put in the low bits of ``tagged`` (0 for the
    noise in the tag of a NaN point)."""
    k = np.int64(_bits_from_float(tagged) & _STAR_TAG)
    return k if k < ns else 0


@nb.njit(inline="always", **FJIT)
def _deepest_cell(tagged, ns, far, x, y, z):
    """The star cell of a point from its tagged max (`_tagged_min`), and whether the point
    left the star: in no cone, or beyond the cell's face opposite the node."""
    k = _tag_cell(tagged, ns)
    f = 1.0 + far[k, 0] * x + far[k, 1] * y + far[k, 2] * z
    return k, (tagged < -BARY_EPS) | (f < -BARY_EPS)


@nb.njit(**JIT)
def _prefetch_groups(q, group_node, star_start, star, coords, simplices, transform, values):
    """Start loading what the tables of the groups after q will read, one hop per group:
    group q + 4's star offsets, q + 3's star list and node, q + 2's cells, q + 1's vertex
    values. Each hop reads only what an earlier one fetched, so none waits for memory (a
    hint: it changes no result)."""
    n_groups = len(group_node)
    nc = values.shape[1]
    if q + 4 < n_groups:
        _prefetch(star_start, group_node[q + 4])
    if q + 3 < n_groups:
        g = group_node[q + 3]
        _prefetch(star, star_start[g])
        _prefetch(star, star_start[g + 1] - 1)
        _prefetch(coords, 3 * g)
    if q + 2 < n_groups:
        g = group_node[q + 2]
        for c in range(star_start[g], star_start[g + 1]):
            s = np.int64(star[c])
            _prefetch(transform, s * 12)
            _prefetch(transform, s * 12 + 11)
            _prefetch(simplices, s * 4)
    if q + 1 < n_groups:
        g = group_node[q + 1]
        for c in range(star_start[g], star_start[g + 1]):
            s = np.int64(star[c])
            for j in range(4):
                v = simplices[s, j] * nc
                _prefetch(values, v)
                _prefetch(values, v + nc - 1)


@nb.njit(inline="always", **FJIT)
def _star_cell_exact(b32, ctol, e0, e1, e2, cone, ns, far, x, y, z):
    """The star cell of a point and whether it left the star, as `_deepest_cell` finds them
    in float64, from the point's float32 tagged max ``b32``: taken from it where its sign is
    sure (beyond ``ctol * |e|_1``, the float32 rounding, and ``2 * BARY_EPS``), else the cone
    test done again in float64."""
    if abs(b32) > ctol * (abs(e0) + abs(e1) + abs(e2)) + np.float32(2 * BARY_EPS):
        k = _tag_cell(b32, ns)
        f = 1.0 + far[k, 0] * x + far[k, 1] * y + far[k, 2] * z
        return k, (b32 < 0) | (f < -BARY_EPS)
    tagged = _tagged_min(_cone_row(cone, 0), 0, x, y, z)
    for k in range(1, ns):
        tagged = max(tagged, _tagged_min(_cone_row(cone, k), k, x, y, z))
    return _deepest_cell(tagged, ns, far, x, y, z)


@nb.njit(inline="always", **FJIT)
def _value_in(res, i, values, g, grad, k, x, y, z):
    """res[i] = values[g] + grad[k] @ (x, y, z) (``grad[k]``: 3 numbers per value column)."""
    for c in range(values.shape[1]):
        res[i, c] = (values[g, c] + grad[k, 3 * c] * x + grad[k, 3 * c + 1] * y) + grad[
            k, 3 * c + 2
        ] * z


@nb.njit(**FJIT)
def _group_block(points, group_start, group_node, q0, q1, simplices, transform, neighbors,
                 coords, values, star_start, star, out, n_max, s_max):  # fmt: skip
    """Groups q0 .. q1-1 of `interpolate_groups`; returns how many points were walked."""
    nc = values.shape[1]
    cone = np.empty((s_max, 9))
    cone32 = np.empty((s_max, 9), dtype=np.float32)
    grad = np.empty((s_max, 3 * nc))
    far = np.empty((s_max, 3))
    e0 = np.empty(n_max, dtype=np.float32)
    e1 = np.empty(n_max, dtype=np.float32)
    e2 = np.empty(n_max, dtype=np.float32)
    thr = np.empty(n_max, dtype=np.float32)
    best = np.empty(n_max, dtype=np.float32)
    out_point = np.empty(n_max, dtype=np.int64)
    out_cell = np.empty(n_max, dtype=np.int64)
    out_next = np.empty(n_max, dtype=np.int64)
    bary = np.empty(4)
    eps2 = np.float32(2 * BARY_EPS)
    walked = 0
    for q in range(q0, q1):
        _prefetch_groups(q, group_node, star_start, star, coords, simplices, transform, values)
        g = group_node[q]
        i0 = group_start[q]
        n = group_start[q + 1] - i0
        c0 = star_start[g]
        ns = star_start[g + 1] - c0
        pts = points[i0 : i0 + n]
        res = out[i0 : i0 + n]
        if ns == 0 or ns > STAR_MAX_CELLS:  # a node in no cell, or a degenerate fan: walk
            s0 = np.int64(star[c0]) if ns > 0 else np.int64(0)
            for i in range(n):
                walked += 1
                s = locate(pts[i], s0, transform, neighbors, bary)
                if s >= 0:
                    _interp_in(s, bary, simplices, values, res[i])
                else:
                    res[i, :] = np.nan
            continue
        ctol, r2 = _cone_tables(
            g, c0, ns, star, simplices, transform, values, cone, cone32, grad, far
        )
        x0, x1, x2 = coords[g, 0], coords[g, 1], coords[g, 2]
        # Flat views: numba's 2-D indexing keeps these loops scalar.
        pf = pts.reshape(-1)
        for i in range(n):  # displacements from g, in float32 for the cone test
            a0 = np.float32(pf[3 * i] - x0)
            a1 = np.float32(pf[3 * i + 1] - x1)
            a2 = np.float32(pf[3 * i + 2] - x2)
            e0[i] = a0
            e1[i] = a1
            e2[i] = a2
            # a tagged max above thr: inside that cell for sure, far face out of reach
            t = ctol * (abs(a0) + abs(a1) + abs(a2)) + eps2
            thr[i] = t if a0 * a0 + a1 * a1 + a2 * a2 < r2 else np.float32(np.inf)
        if q + 1 < len(group_node):  # the next group's points load during the tests
            for j in range(3 * group_start[q + 1], 3 * group_start[q + 2], 8):
                _prefetch(points, j)
        _deepest_cells(cone32, ns, e0, e1, e2, n, best)
        if nc == 3:  # a field: the values of every point from its deepest cell
            rf = res.reshape(-1)
            vg0, vg1, vg2 = values[g, 0], values[g, 1], values[g, 2]
            for i in range(n):
                x = pf[3 * i] - x0
                y = pf[3 * i + 1] - x1
                z = pf[3 * i + 2] - x2
                k = _tag_cell(best[i], ns)
                rf[3 * i] = vg0 + grad[k, 0] * x + grad[k, 1] * y + grad[k, 2] * z
                rf[3 * i + 1] = vg1 + grad[k, 3] * x + grad[k, 4] * y + grad[k, 5] * z
                rf[3 * i + 2] = vg2 + grad[k, 6] * x + grad[k, 7] * y + grad[k, 8] * z
        else:
            for i in range(n):
                k = _tag_cell(best[i], ns)
                _value_in(res, i, values, g, grad, k, pf[3 * i] - x0, pf[3 * i + 1] - x1,
                          pf[3 * i + 2] - x2)  # fmt: skip
        n_unsure = 0
        for i in range(n):  # (thr is inf for a non-finite point: never > it)
            n_unsure += not best[i] > thr[i]
        if n_unsure == 0:
            continue
        # The rest: near a cone's border, near a far face, or outside the star. Decided as in
        # float64; the points outside are walked from the cell they came closest to, after
        # all their first steps' cells were asked for: their memory latencies overlap.
        n_out = 0
        for i in range(n):
            if best[i] > thr[i]:
                continue
            x = pf[3 * i] - x0
            y = pf[3 * i + 1] - x1
            z = pf[3 * i + 2] - x2
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                res[i, :] = np.nan  # a cone test at infinity can pick any cell
                continue
            k, left = _star_cell_exact(best[i], ctol, e0[i], e1[i], e2[i], cone, ns, far, x, y, z)
            if not left:
                if k != _tag_cell(best[i], ns):  # else the value written above stands
                    _value_in(res, i, values, g, grad, k, x, y, z)
                continue
            s = np.int64(star[c0 + k])
            s1 = neighbors[s, _place_in_cell(simplices, s, g)]  # across the far face
            out_point[n_out] = i
            out_cell[n_out] = s
            out_next[n_out] = s1
            n_out += 1
            if s1 >= 0:
                _prefetch(transform, s1 * 12)
                _prefetch(transform, s1 * 12 + 11)
                _prefetch(simplices, s1 * 4)
        for r in range(n_out):
            s1 = out_next[r]
            if s1 >= 0:
                for j in range(4):
                    _prefetch(values, simplices[s1, j] * nc)
        for r in range(n_out):
            i = out_point[r]
            walked += 1
            s = locate(pts[i], out_cell[r], transform, neighbors, bary)
            if s >= 0:
                _interp_in(s, bary, simplices, values, res[i])
            else:
                res[i, :] = np.nan
    return walked


@nb.njit(**dict(PJIT, fastmath={"contract"}))
def interpolate_groups(points, group_start, group_node, simplices, transform, neighbors,
                       coords, values, star_start, star, out):  # fmt: skip
    """Piecewise-linear values at points grouped around nodes (d = 3); NaN outside the mesh.

    Group q holds the points ``group_start[q] .. group_start[q + 1] - 1``, drawn around node
    ``group_node[q]`` (a perturbation sweep's trials). A point near its node lies in one of the
    cones of the node's star: every point of a group is tested against every cell of the star
    in loops without gathers or branches, which the compiler vectorises (the walk's
    table-indexed loads keep it scalar). The test runs in float32, twice the lanes; a point
    whose result is within the bound of float32 rounding of a cone's border, or that could
    reach a far face, is decided again in float64, so the cells are those of a float64 test.
    Points outside the star, or in a star of more than `STAR_MAX_CELLS` cells, are walked
    (`locate`) from the nearest cell. The same values as the walk to rounding (the
    interpolant taken as value at the node plus the cell's gradient times the
    displacement); the same cells but on faces, where either side gives the value.

    Parameters
    ----------
    points : ndarray, shape (k, 3), mm, in the mesh frame
    group_start : ndarray, shape (n_groups + 1,), int64
        Increasing offsets into ``points``, from 0 to k.
    group_node : ndarray, shape (n_groups,), int64
    simplices, transform, neighbors, coords : the mesh (`cfm_fem.interpolation.SimplexMesh`)
    values : ndarray, shape (n, c)
    star_start, star : `node_cells` of the mesh
    out : ndarray, shape (k, c)
        Output: the values (NaN where a walk left the mesh, or the point is not finite).

    Returns
    -------
    int
        Points that were walked.
    """
    n_groups = len(group_node)
    n_max = 1
    for q in range(n_groups):
        n_max = max(n_max, group_start[q + 1] - group_start[q])
    s_max = 1
    for q in range(n_groups):
        g = group_node[q]
        s_max = max(s_max, min(star_start[g + 1] - star_start[g], STAR_MAX_CELLS))
    per = max(1, (1 << 12) // n_max)  # groups per task: ~4k points, work space reused
    walked = 0
    for b in nb.prange((n_groups + per - 1) // per):
        walked += _group_block(points, group_start, group_node, b * per,
                               min(n_groups, (b + 1) * per), simplices, transform, neighbors,
                               coords, values, star_start, star, out, n_max, s_max)  # fmt: skip
    return walked


@nb.njit(**JIT)
def cell_gradient_sums(simplices, transform, values, n_nodes):
    """Measure-weighted sums of the cell gradients of a piecewise-linear field, per node.

    Parameters
    ----------
    simplices : ndarray, shape (m, d + 1), int
    transform : ndarray, shape (m, d + 1, d)
        scipy-layout barycentric transforms: rows j < d are grad(lambda_j), 1/mm.
    values : ndarray, shape (n_nodes, 3), T
    n_nodes : int

    Returns
    -------
    acc : ndarray, shape (n_nodes, 3, d), T/mm x (1/|det T|)
        Sum over the cells incident to each node of |1/det T| (proportional to the cell's
        measure) times the cell's gradient [c, a] = dB_c/dx_a, in local coordinates.
    wsum : ndarray, shape (n_nodes,)
        Sum of those weights. A degenerate cell (NaN transform) makes its nodes' sums NaN.
    """
    m, k = simplices.shape
    d = k - 1
    acc = np.zeros((n_nodes, 3, d))
    wsum = np.zeros(n_nodes)
    cg = np.empty((3, d))
    for s in range(m):
        t = transform[s]
        if d == 3:
            det = (t[0, 0] * (t[1, 1] * t[2, 2] - t[1, 2] * t[2, 1])
                   - t[0, 1] * (t[1, 0] * t[2, 2] - t[1, 2] * t[2, 0])
                   + t[0, 2] * (t[1, 0] * t[2, 1] - t[1, 1] * t[2, 0]))  # fmt: skip
        else:
            det = t[0, 0] * t[1, 1] - t[0, 1] * t[1, 0]
        w = abs(1.0 / det)
        for c in range(3):
            last = values[simplices[s, d], c]
            for a in range(d):
                g = 0.0
                for j in range(d):  # grad(lambda_d) = -sum_j grad(lambda_j)
                    g += (values[simplices[s, j], c] - last) * t[j, a]
                cg[c, a] = g * w
        for j in range(k):
            v = simplices[s, j]
            wsum[v] += w
            for c in range(3):
                for a in range(d):
                    acc[v, c, a] += cg[c, a]
    return acc, wsum


# ---------------------------------------------------------------------------------------------
# Order statistics without a full sort (O(n) per node instead of O(n log n)).
# ---------------------------------------------------------------------------------------------
@nb.njit(**JIT)
def select_inplace(a, lo, hi, k):
    """Partially order ``a[lo:hi+1]`` so that ``a[k]`` is its (k-lo)-th smallest value.

    Hoare partitioning (Wirth's select) with a median-of-three pivot: linear on average and
    robust to ties. Afterwards ``a[lo:k] <= a[k] <= a[k+1:hi+1]``.
    """
    while hi > lo:
        mid = (lo + hi) // 2
        x0, x1, x2 = a[lo], a[mid], a[hi]
        if x0 > x1:
            x0, x1 = x1, x0
        if x1 > x2:
            x1 = x2
            if x0 > x1:
                x1 = x0
        x = x1
        i, j = lo, hi
        while i <= j:
            while a[i] < x:
                i += 1
            while x < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if j < k:
            lo = i
        if k < i:
            hi = j


@nb.njit(**JIT)
def _insertion_sort(a, src):
    """a[:len(src)] = sorted(src); exact, fast when src is nearly sorted or short."""
    for i in range(src.shape[0]):
        x = src[i]
        j = i
        while j > 0 and a[j - 1] > x:
            a[j] = a[j - 1]
            j -= 1
        a[j] = x


@nb.njit(**JIT)
def sort_values(a):
    """Sort a float64 array in place (NaN last, as `numpy.sort`).

    Comparison sorts stall on mispredicted branches (numba's quicksort: ~80 ns per element for
    500 values). Here the values are first ordered by a key quantised over [min, max], then an
    insertion pass orders values sharing a key exactly:

    - up to 4,096 values (the tails of 10,000 trials), one counting pass over 256 to 4,096
      keys (about as many as values: few share one, and even a sample whose values all share
      one key costs at most a few ms); ~6 ns per element for 100 to 4,000 values;
    - above, an LSD radix sort on a 24-bit key (3 branch-free passes of 8 bits).
    """
    n = a.shape[0]
    if n < 48:
        _insertion_sort(a, a.copy())
        return
    lo = a[0]
    hi = a[0]
    nan = False
    for i in range(n):
        lo = min(lo, a[i])
        hi = max(hi, a[i])
        nan |= a[i] != a[i]
    if nan:  # a trial that met a slab's halo sentinel (NaN field): its key would index out
        # of the counting arrays. NaN go last, as numpy's; the node's statistics are NaN anyway.
        k = 0  # (not np.sort: its quicksort would add ~3 s to every first run's compile)
        for i in range(n):
            v = a[i]
            if v == v:
                a[k] = v
                k += 1
        a[k:] = np.nan
        if k < 48:
            _insertion_sort(a[:k], a[:k].copy())
            return
        n = k
        lo = a[0]
        hi = a[0]
        for i in range(n):
            lo = min(lo, a[i])
            hi = max(hi, a[i])
    _sort_finite(a[:n], lo, hi)


@nb.njit(**JIT)
def _sort_finite(a, lo, hi):
    """`sort_values` for 48 or more finite values in [lo, hi]."""
    n = a.shape[0]
    if not hi > lo:
        return
    if n <= 4096:
        _bucket_sort(a, n, lo, hi)
        return
    scale = 16777215.0 / (hi - lo)
    src_v = a.copy()
    dst_v = np.empty(n)
    src_k = np.empty(n, dtype=np.uint32)
    dst_k = np.empty(n, dtype=np.uint32)
    for i in range(n):
        src_k[i] = np.uint32(min((src_v[i] - lo) * scale, 16777215.0))
    counts = np.empty(256, dtype=np.int64)
    for sh in range(0, 24, 8):
        counts[:] = 0
        for i in range(n):
            counts[(src_k[i] >> sh) & 255] += 1
        tot = 0
        for b in range(256):
            c = counts[b]
            counts[b] = tot
            tot += c
        for i in range(n):
            b = (src_k[i] >> sh) & 255
            j = counts[b]
            counts[b] = j + 1
            dst_v[j] = src_v[i]
            dst_k[j] = src_k[i]
        src_v, dst_v = dst_v, src_v
        src_k, dst_k = dst_k, src_k
    _insertion_sort(a, src_v)


@nb.njit(**JIT)
def _bucket_sort(a, n, lo, hi):
    """`sort_values` for 48 <= n <= 4096 values in [lo, hi], lo < hi: one counting pass over
    a power of two (>= n, >= 256) of keys, then the exact insertion pass."""
    nk = 256
    while nk < n:
        nk *= 2
    top = np.float64(nk - 1)
    scale = top / (hi - lo)
    keys = np.empty(n, dtype=np.int64)
    start = np.zeros(nk + 1, dtype=np.int64)
    for i in range(n):
        k = np.int64(min((a[i] - lo) * scale, top))
        keys[i] = k
        start[k + 1] += 1
    for k in range(nk):
        start[k + 1] += start[k]
    by_key = np.empty(n)
    for i in range(n):
        k = keys[i]
        j = start[k]
        start[k] = j + 1
        by_key[j] = a[i]
    _insertion_sort(a, by_key)


#: Tails beyond mean -+ TAIL_SIGMAS * std are gathered first; 1.3 holds ~10 % of a normal sample,
#: twice the 5 % the intervals need. Fewer than needed falls back to the whole sample (exact).
TAIL_SIGMAS = 1.3
#: Leading values whose mean and std place the tail thresholds (`sums_and_tails`).
TAIL_PILOT = 512


@nb.njit(**_RJIT)
def _pilot_mean_std(x, m):
    """Mean and std (ddof 1) of x[:m], m >= 1, summed in any order (vectorised): they only
    place the tail thresholds of `sums_and_tails`, never a result."""
    pm = 0.0
    for i in range(m):
        pm += x[i]
    pm /= m
    pv = 0.0
    for i in range(m):
        pv += (x[i] - pm) ** 2
    return pm, np.sqrt(pv / max(m - 1, 1))


@nb.njit(**JIT)
def sums_and_tails(x, n, scratch, end):
    """Shifted sums of x[:n] and its two tails, in one pass.

    Parameters
    ----------
    x : ndarray, shape (>= n,)
    n : int
    scratch : ndarray, shape (>= end,)
        Receives the low tail at scratch[:n_lo] and the high tail at scratch[end - n_hi:end]
        (unsorted); end >= n.
    end : int

    Returns
    -------
    shift, s1, s2 : float
        shift = x[0]; s1, s2: sums of (x - shift) and its square, in index order.
    n_lo, n_hi : int
        Sizes of the tails: values <= t_lo and >= t_hi, t = mean -+ TAIL_SIGMAS std of the first
        TAIL_PILOT values (no tails if those are constant). The thresholds only decide how much
        is gathered, never a result: a caller needing the h extreme values takes the tail path
        only when n_lo, n_hi >= h. t_lo < t_hi, so n_lo + n_hi <= n.
    """
    if n == 0:
        return 0.0, 0.0, 0.0, 0, 0
    shift = x[0]
    pm, ps = _pilot_mean_std(x, min(n, TAIL_PILOT))
    t_lo = pm - TAIL_SIGMAS * ps
    t_hi = pm + TAIL_SIGMAS * ps
    if not t_lo < t_hi:  # constant pilot: no tails (the caller's whole-sample path), and never
        t_lo = -np.inf  # a value in both tails, which would overlap in scratch
        t_hi = np.inf
    s1 = 0.0
    s2 = 0.0
    n_lo = 0
    n_hi = 0
    for i in range(n):  # branch-free gather, fused with the sums (one read of x)
        v = x[i]
        dv = v - shift
        s1 += dv
        s2 += dv * dv
        scratch[n_lo] = v
        n_lo += v <= t_lo
        scratch[end - 1 - n_hi] = v
        n_hi += v >= t_hi
    return shift, s1, s2, n_lo, n_hi


@nb.njit(**JIT)
def sample_stats(a, n, q, out, scratch):
    """Mean, std and the coverage intervals of the first ``n`` values of ``a``.

    Parameters
    ----------
    a : ndarray, shape (>= n,)
        Samples; reordered in place only on the fallback path.
    n : int
        Number of samples.
    q : int
        Samples spanned by the coverage interval, see `cfm_fem.mc.coverage_count`.
    out : ndarray, shape (6,)
        mean, std (ddof 1), symmetric low, symmetric high, shortest low, shortest high
        (JCGM 101 7.7); NaN when n < 2.
    scratch : ndarray, shape (>= n,)
        Work space.

    Notes
    -----
    Every order statistic the two intervals need lies among the h = n - q smallest or the h
    largest values. Those are taken from the tails beyond mean -+ 1.3 std (`sums_and_tails`;
    selection in the whole sample if a tail is too thin) and then sorted: O(n), not a full sort.
    """
    if n < 2:
        for j in range(6):
            out[j] = np.nan
        return
    # one pass, shifted by the first value so the variance keeps its precision
    shift, s1, s2, n_lo, n_hi = sums_and_tails(a, n, scratch, n)
    mean = shift + s1 / n
    std = np.sqrt(max(s2 - s1 * s1 / n, 0.0) / (n - 1))
    out[0] = mean
    out[1] = std
    h = n - q
    if n_lo >= h and n_hi >= h and std > 0.0:
        # sorting a whole gathered tail (~2h values) costs less than selecting h of them first
        lo = scratch[:n_lo]
        hi = scratch[n - n_hi : n]
        sort_values(lo)
        sort_values(hi)
        low = lo[:h]
        high = hi[n_hi - h :]
    else:
        select_inplace(a, np.int64(0), n - 1, h - 1)  # a literal 0 compiles a 2nd version
        select_inplace(a, h, n - 1, q)
        low = a[:h]
        high = a[q:n]
        sort_values(low)
        sort_values(high)
    _intervals(low, high, n, q, out)


@nb.njit(**JIT)
def _intervals(low, high, n, q, out):
    """Symmetric and shortest intervals into out[2:6] from the h = n - q smallest values
    (``low``, ascending) and the h largest (``high``, ascending: high[j] is order statistic
    q + j, 0-based)."""
    h = n - q
    r = (n - q) // 2 if (n - q) % 2 == 0 else (n - q + 1) // 2
    if r < 1:
        r = 1
    out[2] = low[r - 1]
    out[3] = high[r - 1]
    best = 0
    for j in range(1, h):
        if high[j] - low[j] < high[best] - low[best]:
            best = j
    out[4] = low[best]
    out[5] = high[best]


@nb.njit(**JIT)
def _merged_stats(x, n_in, shift, s1, s2, lo_tail, hi_tail, r, y, m, p, out, low, high, full,
                  scratch):  # fmt: skip
    """Statistics of the union of r * x[:n_in] (r > 0) and y[:m] (y sorted ascending).

    ``s1``, ``s2``: sums of (x - shift) and its square over x[:n_in]; ``lo_tail``/``hi_tail``:
    the smallest / largest values of x[:n_in], sorted ascending (scaling by r > 0 keeps the
    order). The union's h smallest values are among the h smallest of r * x and all of y, so
    merging two sorted lists gives the exact order statistics without touching all n values.
    Falls back to `sample_stats` on the whole union when a tail is shorter than h.
    ``low``, ``high``, ``full``, ``scratch``: work space (>= n_in + m).
    """
    n = n_in + m
    if n < 2:
        for j in range(6):
            out[j] = np.nan
        return
    q = coverage_count(n, p)
    h = n - q
    n_lo = lo_tail.shape[0]
    n_hi = hi_tail.shape[0]
    if n_lo < h or n_hi < h:
        for j in range(n_in):
            full[j] = r * x[j]
        for j in range(m):
            full[n_in + j] = y[j]
        sample_stats(full, n, q, out, scratch)
        return
    c = r * shift  # shifted sums keep the variance free of cancellation
    t1 = r * s1
    t2 = r * r * s2
    for j in range(m):
        dv = y[j] - c
        t1 += dv
        t2 += dv * dv
    out[0] = c + t1 / n
    out[1] = np.sqrt(max(t2 - t1 * t1 / n, 0.0) / (n - 1))
    i = 0
    j = 0
    for k in range(h):  # the h smallest: merge ascending
        if j < m and (i >= n_lo or y[j] < r * lo_tail[i]):
            low[k] = y[j]
            j += 1
        else:
            low[k] = r * lo_tail[i]
            i += 1
    i = n_hi - 1
    j = m - 1
    for k in range(h - 1, -1, -1):  # the h largest: merge descending
        if j >= 0 and (i < 0 or y[j] > r * hi_tail[i]):
            high[k] = y[j]
            j -= 1
        else:
            high[k] = r * hi_tail[i]
            i -= 1
    _intervals(low, high, n, q, out)


@nb.njit(**JIT)
def coverage_count(n, p):
    """Numba twin of `cfm_fem.mc.coverage_count`."""
    pm = p * n
    if abs(pm - np.round(pm)) < 1e-9:
        q = int(np.round(pm))
    else:
        q = int(pm + 0.5)
    return min(max(q, 1), n - 1)


# ---------------------------------------------------------------------------------------------
# Gaussian perturbation sweep (paper eq. 16), statistics streamed per node.
# ---------------------------------------------------------------------------------------------
#: Layout of the last axis of the statistics array.
STAT_NAMES = ("mean", "std", "sym_lo", "sym_hi", "short_lo", "short_hi")
#: Layout of the component axis: the three components and |B|.
COMPONENTS = ("Bx", "By", "Bz", "absB")


@nb.njit(**JIT)
def _star_contains(simplices, s, node):
    for j in range(simplices.shape[1]):
        if simplices[s, j] == node:
            return True
    return False


#: Largest star (cells incident to one node) handled by the star tables; larger stars (rare
#: in FEM meshes, about 24 tetrahedra is typical) take the global walk.
MAX_STAR = 256


#: `star_locate`: the displacement's ray leaves the mesh through a boundary face at the node.
LEAVES_MESH = -3
#: Slots of the open-addressing table that maps a cell to its index in the star (2 x MAX_STAR).
STAR_HASH = 2 * MAX_STAR


@nb.njit(inline="always", **JIT)
def _star_slot(htab, g, s, n):
    """Index of cell s in the star of g being built; inserts it as index n if absent (returns
    -1 - n then). ``htab`` (3, STAR_HASH) int64 rows: cell, index, owner node (a slot owned
    by another node is free; `build_star` clears the owners first, else a node built a second
    time would find its own entries of the first time)."""
    h = np.int64((np.uint64(s) * GAMMA) >> np.uint64(55)) & (STAR_HASH - 1)
    while htab[2, h] == g:
        if htab[0, h] == s:
            return htab[1, h]
        h = (h + 1) & (STAR_HASH - 1)
    htab[0, h] = s
    htab[1, h] = n
    htab[2, h] = g
    return -1 - n


@nb.njit(**JIT)
def build_star(g, c0, simplices, transform, neighbors, values, cells, lmat, dmat, nbr, htab):
    """Tables of the star of node ``g``: the cells incident to it, reached from ``c0`` across
    faces that contain ``g``.

    A point ``x_g + delta`` lies in star cell i when the barycentric coordinates of the cell's
    other vertices, ``lam = lmat[i] @ delta``, are >= 0 and ``1 - sum(lam) >= 0`` (that of g);
    the field there is ``B_g + dmat[i] @ lam``. Working with the small displacement instead of
    the absolute position avoids cancelling map coordinates of ~100 mm against U_p ~ 1e-2 mm.

    Parameters
    ----------
    g, c0 : int
        Node and a cell incident to it.
    simplices, transform, neighbors : `SimplexMesh` arrays (d + 1 vertices per cell)
    values : ndarray, shape (n, 3), T
    cells : ndarray, shape (MAX_STAR,), int64
        Output: global index of each star cell.
    lmat : ndarray, shape (MAX_STAR, d, d), 1/mm
        Output: row a maps delta to the barycentric coordinate of the a-th vertex other than g.
    dmat : ndarray, shape (MAX_STAR, 3, d), T
        Output: column a is B of that vertex minus B_g.
    nbr : ndarray, shape (MAX_STAR, d), int64
        Output: star index of the cell across the face opposite that vertex (the face contains
        g); -1 across the mesh boundary.
    htab : ndarray, shape (3, STAR_HASH), int64
        Work space (see `_star_slot`); its owner row is cleared here.

    Returns
    -------
    int
        Number of star cells; -1 if ``c0`` does not contain ``g``, the star exceeds MAX_STAR or
        a face with g leads to a cell without it.
    """
    d = transform.shape[2]
    if c0 < 0 or not _star_contains(simplices, c0, g):
        return -1
    htab[2, :] = -1  # 512 stores: a star built before for g (a node listed twice) is gone
    cells[0] = c0
    _star_slot(htab, g, c0, 0)
    n = 1
    i = 0
    while i < n:  # breadth-first across the faces that contain g, filling the tables
        s = cells[i]
        a = 0
        for j in range(d + 1):
            v = simplices[s, j]
            if v == g:
                continue
            ns = neighbors[s, j]
            if ns < 0:
                nbr[i, a] = -1
            else:
                k = _star_slot(htab, g, ns, n)
                if k < 0:
                    # too large; or a cell without g across a face with g: not a conforming
                    # star (the sentinel cell a slab's halo border leads to, `cfm_fem.slabs`)
                    if n == cells.shape[0] or not _star_contains(simplices, ns, g):
                        return -1
                    cells[n] = ns
                    k = n
                    n += 1
                nbr[i, a] = k
            for b in range(d):
                if j < d:
                    lmat[i, a, b] = transform[s, j, b]
                else:  # the last coordinate is 1 - the others
                    acc = 0.0
                    for m in range(d):
                        acc += transform[s, m, b]
                    lmat[i, a, b] = -acc
            for c in range(3):
                dmat[i, c, a] = values[v, c] - values[g, c]
            a += 1
        i += 1
    return n


@nb.njit(inline="always", **JIT)
def star_locate(start, lmat, nbr, n_star, delta, lam):
    """Star cell containing ``x_g + delta`` by walking across faces that contain g.

    Returns the star index (``lam`` then holds the barycentric coordinates of the cell's
    vertices other than g); LEAVES_MESH if the walk crosses a boundary face of the mesh (such a
    face contains g, so every displacement along the same ray, whatever U_p, leaves the mesh
    there too); -1 if the point is beyond the star (past a face opposite g) or the walk does not
    settle.
    """
    d = lmat.shape[2]
    s = start
    for _ in range(n_star + 4):
        lmin = np.inf
        amin = 0
        tot = 0.0
        for a in range(d):
            v = 0.0
            for b in range(d):
                v += lmat[s, a, b] * delta[b]
            lam[a] = v
            tot += v
            if v < lmin:
                lmin = v
                amin = a
        if lmin >= -BARY_EPS:
            return s if 1.0 - tot >= -BARY_EPS else -1
        s = nbr[s, amin]
        if s < 0:
            return LEAVES_MESH
    return -1


@nb.njit(inline="always", **JIT)
def star_locate3(start, lmat, nbr, n_star, d0, d1, d2):
    """`star_locate` written out for d = 3 (the hot loop of 3-D maps).

    Returns (cell or code as `star_locate`, lam0, lam1, lam2): values, not an output array,
    and the face to cross chosen by selects, so the only unpredictable branch is the exit.
    """
    s = start
    for _ in range(n_star + 4):
        l0 = lmat[s, 0, 0] * d0 + lmat[s, 0, 1] * d1 + lmat[s, 0, 2] * d2
        l1 = lmat[s, 1, 0] * d0 + lmat[s, 1, 1] * d1 + lmat[s, 1, 2] * d2
        l2 = lmat[s, 2, 0] * d0 + lmat[s, 2, 1] * d1 + lmat[s, 2, 2] * d2
        m01 = min(l0, l1)
        if min(m01, l2) >= -BARY_EPS:
            return (s if 1.0 - (l0 + l1 + l2) >= -BARY_EPS else -1), l0, l1, l2
        a = 2 if l2 < m01 else (1 if l1 < l0 else 0)  # the most negative (first on ties)
        s = nbr[s, a]
        if s < 0:
            return LEAVES_MESH, l0, l1, l2
    return -1, 0.0, 0.0, 0.0


@nb.njit(inline="always", **JIT)
def _star_bary(lmat, i, delta, lam):
    """``lam[:d] = lmat[i] @ delta``: in star cell i, the barycentric coordinates of its
    vertices other than g at ``x_g + delta``; returns their sum and their minimum."""
    d = lmat.shape[2]
    tot = 0.0
    lmin = np.inf
    for a in range(d):
        v = 0.0
        for b in range(d):
            v += lmat[i, a, b] * delta[b]
        lam[a] = v
        tot += v
        lmin = min(lmin, v)
    return tot, lmin


@nb.njit(**JIT)
def star_exact(g, cells, n_star, simplices, excess):
    """Whether LEAVES_MESH is a proven verdict at node g: every border face of its star (they
    all contain g) is a supporting plane of the whole mesh (zero `face_excess`).

    A displacement beyond such a face's plane leaves the mesh at every U_p. Behind a face
    with an excess (a re-entrant edge or corner at g, a notch facing it, a face left by
    removed hull slivers), the point may lie in another star cell or in a cell further away:
    `star_recheck` places those trials.

    Parameters
    ----------
    g : int
    cells : ndarray, shape (>= n_star,), int64
        The star's cells (`build_star`).
    simplices : ndarray, shape (m, d + 1), int64
    excess : ndarray, shape (m, d + 1) or (0, d + 1)
        Empty for a convex mesh (every verdict proven; nothing is read).
    """
    if excess.shape[0] == 0:
        return True
    for i in range(n_star):
        s = cells[i]
        for j in range(simplices.shape[1]):
            if simplices[s, j] != g and excess[s, j] > 0.0:
                return False
    return True


@nb.njit(**JIT)
def star_find(p, g, coords, transform, cells, n_star, lmat, delta, bary):
    """The cell of the star of g that holds ``p``, testing them all, or OUTSIDE.

    Exact for a point nearer to g than any other cell (`node_reach`): it is then in a star
    cell or outside the mesh.

    Parameters
    ----------
    p : ndarray, shape (d,), mm
    g : int
    coords, transform : mesh arrays
    cells, n_star, lmat : star tables (`build_star`)
    delta : ndarray, shape (d,)
        Work space.
    bary : ndarray, shape (d + 1,)
        Output: barycentric coordinates in the cell found (as `locate` computes them).

    Returns
    -------
    int
        The cell (mesh index), or OUTSIDE.
    """
    d = lmat.shape[2]
    for a in range(d):
        delta[a] = p[a] - coords[g, a]
    for i in range(n_star):
        tot, lmin = _star_bary(lmat, i, delta, bary)  # bary: scratch until the cell is found
        if lmin >= -BARY_EPS and 1.0 - tot >= -BARY_EPS:
            _bary_in(p, cells[i], transform, bary)
            return cells[i]
    return OUTSIDE


@nb.njit(**JIT)
def star_behind(g, coords, cells, n_star, lmat, nbr, simplices, cand, free):
    """The star cells of g that reach beyond the plane of a border face of the star (such a
    face contains g): those with a vertex strictly beyond it; and the border faces no star
    cell reaches beyond.

    A displacement the star walk finds beyond a border face's plane (LEAVES_MESH) can lie only
    in the cone of one of the cells; none (a star convex at g): in no star cell. Beyond the
    plane of a free face, it is in no star cell either (every star cell lies on its inner
    side): on a faceted curved surface, where few stars are convex at g, most exits are proven
    so, at the cost of one face test (`star_exit`).

    Parameters
    ----------
    g : int
    coords : ndarray, shape (n, d), mm
    cells, n_star, lmat, nbr : star tables (`build_star`)
    simplices : ndarray, shape (m, d + 1), int64
    cand : ndarray, shape (>= n_star,), int64
        Output: star indices of those cells.
    free : ndarray, shape (2, >= n_star * d), int64
        Output: the free border faces, as columns (i, a): star cell i, face opposite its a-th
        vertex other than g (see `build_star`).

    Returns
    -------
    n_cand, n_free : int
        How many of each.
    """
    d = lmat.shape[2]
    hit = np.zeros(n_star, dtype=np.bool_)
    n_free = 0
    for i in range(n_star):
        for a in range(d):
            if nbr[i, a] >= 0:
                continue
            face_free = True
            for i2 in range(n_star):
                s = cells[i2]
                for j in range(simplices.shape[1]):
                    v = simplices[s, j]
                    lam = 0.0
                    for b in range(d):
                        lam += lmat[i, a, b] * (coords[v, b] - coords[g, b])
                    if lam < -1e-12:  # beyond the plane (rounding: ~1e-16)
                        hit[i2] = True
                        face_free = False
            free[0, n_free] = i
            free[1, n_free] = a
            n_free += face_free
    n_cand = 0
    for i2 in range(n_star):
        cand[n_cand] = i2
        n_cand += hit[i2]
    return n_cand, n_free


#: `star_exit`: the point is not nearer to g than every other cell; `star_recheck` places it.
BEYOND_REACH = -4


@nb.njit(inline="always", **JIT)
def star_exit(lmat, reach, cand, n_cand, free, n_free, delta, lam):
    """Place ``x_g + delta`` whose star walk crossed a border face (LEAVES_MESH), at a node
    where that proves nothing (`star_exact` False).

    Nearer to g than any other cell (``|delta| < reach``, `node_reach`), the point is in a
    star cell or outside: beyond the plane of a free face it is outside; else only the cells of
    `star_behind` can hold it. Farther, the caller tests every star cell (`star_recheck`; not
    called from here: a call that may happen makes numba count references to its array
    arguments on every call, ~100 ns).

    Parameters
    ----------
    lmat : star table (`build_star`)
    reach : float, mm
        `node_reach` of g.
    cand, n_cand, free, n_free : `star_behind` of g
    delta : ndarray, shape (d,), mm
    lam : ndarray, shape (d,)
        Output: barycentric coordinates in the star cell found.

    Returns
    -------
    cell : int
        Star index of the cell holding the point; LEAVES_MESH: outside at every fraction
        r <= 1 of ``delta``; -1: the global walk; BEYOND_REACH: `star_recheck`, with
    r_in, r_out : float
        ``x_g + r delta`` proven outside for r < r_in and r > r_out.
    """
    d = lmat.shape[2]
    n2 = 0.0
    for a in range(d):
        n2 += delta[a] * delta[a]
    if n2 >= reach * reach:
        return BEYOND_REACH, 0.0, np.inf
    for f in range(n_free):  # beyond a plane through g that every star cell stays behind
        i = free[0, f]
        a = free[1, f]
        v = 0.0
        for b in range(d):
            v += lmat[i, a, b] * delta[b]
        if v < -BARY_EPS:
            return LEAVES_MESH, 0.0, np.inf
    cone = False
    for c in range(n_cand):
        i = cand[c]
        tot = 0.0
        in_cone = True
        for a in range(d):
            v = 0.0
            for b in range(d):
                v += lmat[i, a, b] * delta[b]
            if v < -BARY_EPS:  # not in this cell's cone: the other rows are not needed
                in_cone = False
                break
            lam[a] = v
            tot += v
        if in_cone:
            if 1.0 - tot >= -BARY_EPS:
                return i, 0.0, np.inf
            cone = True  # inside for small r, beyond the cell at r = 1: the global walk
    return (-1 if cone else LEAVES_MESH), 0.0, np.inf


@nb.njit(**JIT)
def star_recheck(g, cells, n_star, lmat, nbr, simplices, excess, reach, delta, lam):
    """Place ``x_g + delta`` whose star walk crossed a border face, at a node where that is no
    proof of leaving the mesh (`star_exact` False).

    Every star cell is tested. Else the point is beyond the star, and ``x_g + r delta`` is
    proven outside for the fractions r where it either lies beyond a border face of the star
    by more than every node of the mesh (``-r lam_a > excess``), or, if ``delta`` is in no star
    cell's cone, is nearer to g than any other cell (``r |delta| < reach``, `node_reach`).

    Parameters
    ----------
    g : int
    cells, n_star, lmat, nbr : star tables (`build_star`)
    simplices : ndarray, shape (m, d + 1), int64
    excess : ndarray, shape (m, d + 1)
        `face_excess` in heights of the cell above the face.
    reach : float, mm
        `node_reach` of g.
    delta : ndarray, shape (d,), mm
    lam : ndarray, shape (d,)
        Output: barycentric coordinates in the star cell found.

    Returns
    -------
    cell : int
        Star index of the cell holding the point, or -1 (beyond the star).
    r_in, r_out : float
        With cell -1: the point ``x_g + r delta`` is outside the mesh for every r < r_in and
        every r > r_out (0 and inf where nothing proves it).
    """
    d = lmat.shape[2]
    r_out = np.inf
    cone = False  # delta in some star cell's cone: x_g + r delta is inside for small r
    norm = 0.0
    for a in range(d):
        norm += delta[a] * delta[a]
    for i in range(n_star):
        tot, lmin = _star_bary(lmat, i, delta, lam)
        if lmin >= -BARY_EPS:
            if 1.0 - tot >= -BARY_EPS:
                return i, 0.0, np.inf
            cone = True
        s = cells[i]
        a = 0
        for j in range(d + 1):
            if simplices[s, j] == g:
                continue
            if nbr[i, a] < 0 and lam[a] < -BARY_EPS:  # beyond this border face's plane
                r_out = min(r_out, (excess[s, j] * (1.0 + EXCESS_MARGIN) + BARY_EPS) / -lam[a])
            a += 1
    r_in = 0.0 if cone else reach / math.sqrt(norm)
    return -1, r_in, r_out


#: Levels per axis of an octahedral direction bin (`direction_bin`).
BIN_LEVELS = 4


def n_direction_bins(d: int) -> int:
    """Number of `direction_bin` values in d dimensions (128 in 3-D, 16 in 2-D)."""
    return (1 << d) * BIN_LEVELS ** (d - 1)


@nb.njit(inline="always", **JIT)
def direction_bin(delta, d):
    """Octahedral bin of a displacement direction: its sign pattern and, for each axis but the
    last, the share |delta_a| / sum_b |delta_b| in BIN_LEVELS equal steps.

    The bins are cells of a square grid on the faces of the octahedron |x| + |y| + |z| = 1, so
    every bin is a convex cone of directions. A walk started from the star cell of the bin's
    centre direction (`star_bin_starts`) ends after at most one step for ~94 % of the
    displacements of a typical 3-D Delaunay star (~27 cells). Planar maps start their star
    walks so; 3-D maps test every star cell instead (`star_errors3`).
    """
    tot = 0.0
    b = 0
    for a in range(d):
        tot += abs(delta[a])
        b = 2 * b + (1 if delta[a] < 0.0 else 0)
    inv = BIN_LEVELS / tot if tot > 0.0 else 0.0
    for a in range(d - 1):
        b = BIN_LEVELS * b + min(np.int64(abs(delta[a]) * inv), BIN_LEVELS - 1)
    return b


@nb.njit(**JIT)
def _bin_centre(b, d, scale, delta):
    """A direction inside bin b (inverse of `direction_bin`) of 1-norm ``scale``; False for the
    bins that no direction reaches (level sum >= BIN_LEVELS)."""
    rest = b
    lsum = 0
    for a in range(d - 2, -1, -1):  # the last level is the lowest digit
        delta[a] = rest % BIN_LEVELS
        lsum += rest % BIN_LEVELS
        rest //= BIN_LEVELS
    if lsum >= BIN_LEVELS:
        return False
    # the square's centre, or the centroid of its feasible corner where the face's edge cuts it
    off = 0.5 if lsum + 0.5 * (d - 1) < BIN_LEVELS else 1.0 / d
    tot = 0.0
    for a in range(d - 1):
        delta[a] = (delta[a] + off) / BIN_LEVELS
        tot += delta[a]
    delta[d - 1] = 1.0 - tot
    for a in range(d - 1, -1, -1):
        delta[a] *= -scale if rest & 1 else scale
        rest >>= 1
    return True


@nb.njit(**JIT)
def star_bin_starts(lmat, nbr, n_star, d, scale, out):
    """Start cell of every `direction_bin`: the star cell of the bin's centre direction. Each
    walk starts where the previous bin's ended (neighbouring bins, short walks)."""
    delta = np.empty(d)
    lam = np.empty(d)
    s = 0
    for b in range(out.shape[0]):
        if _bin_centre(b, d, scale, delta):
            r = star_locate(s, lmat, nbr, n_star, delta, lam)
            if r >= 0:
                s = r
        out[b] = s


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


@nb.njit(inline="always", **JIT)
def _lam3(lmat, s, d0, d1, d2):
    """Barycentric coordinates of the star cell s's vertices other than g at displacement d."""
    return (
        lmat[s, 0, 0] * d0 + lmat[s, 0, 1] * d1 + lmat[s, 0, 2] * d2,
        lmat[s, 1, 0] * d0 + lmat[s, 1, 1] * d1 + lmat[s, 1, 2] * d2,
        lmat[s, 2, 0] * d0 + lmat[s, 2, 1] * d1 + lmat[s, 2, 2] * d2,
    )


@nb.njit(inline="always", **JIT)
def _err3(dmat, s, l0, l1, l2):
    """B - B_g in star cell s at barycentric coordinates lam (the scalar path's order)."""
    return (
        0.0 + dmat[s, 0, 0] * l0 + dmat[s, 0, 1] * l1 + dmat[s, 0, 2] * l2,
        0.0 + dmat[s, 1, 0] * l0 + dmat[s, 1, 1] * l1 + dmat[s, 1, 2] * l2,
        0.0 + dmat[s, 2, 0] * l0 + dmat[s, 2, 1] * l1 + dmat[s, 2, 2] * l2,
    )


@nb.njit(inline="always", **JIT)
def _unit_disp(w, z, t, a):
    """Component a of trial t's displacement per unit U_p: sum_c w[c, a] z[c, t], summed in the
    order `star_errors3` uses (the same bits on every path)."""
    return 0.0 + w[0, a] * z[0, t] + w[1, a] * z[1, t] + w[2, a] * z[2, t]


@nb.njit(**FJIT)
def _deepest_cells(cone, n_star, d0, d1, d2, n, tag):
    """``tag[t]``: the max over star cells k < n_star of `_tagged_min` of displacement t (the
    cone rows of cell k in ``cone[k]``, 9 numbers): the deepest cell of each displacement and
    how deep, in vectorised loops over the displacements."""
    c = _cone_row(cone, 0)
    for t in range(n):
        tag[t] = _tagged_min(c, 0, d0[t], d1[t], d2[t])
    for k in range(1, n_star):
        c = _cone_row(cone, k)
        for t in range(n):
            tag[t] = max(tag[t], _tagged_min(c, k, d0[t], d1[t], d2[t]))


@nb.njit(**JIT)
def star_errors3(z, n, w, smax, lmat, dmat, nbr, n_star, err, dl, tag, rest, code):
    """Field errors of n trials located in the star tables of a 3-D node, in blocks.

    Trial t moves the probe by ``delta = smax * (w.T @ z[:, t])``, computed in a vectorised
    loop. Every trial is then tested against every cell of the star, in vectorised loops over
    the trials (`interpolate_groups`' cone test: the deepest cell kept as a float tagged with
    its index), and its error written from that cell when it lies inside; the rest walk the
    star from that cell (`star_locate3`), which gives the reason. Same cells, so the same
    errors, as walking every trial (but for trials within rounding of a face between two
    cells, where the walk may stop in either).

    Parameters
    ----------
    z : ndarray, shape (3, >= n)
        Standard normals per trial.
    w : ndarray, shape (3, 3)
        Row c: the mesh-frame displacement per unit normal c (basis[c] * sigma_axes[c]);
        components summed as in `_unit_disp`.
    smax : float, mm
    lmat, dmat, nbr, n_star : star tables (`build_star`), n_star <= MAX_STAR.
    err : ndarray, shape (3, >= n), T
        Output: B(x + delta) - B(x) of each trial found in the star (others left as they are).
    dl : ndarray, shape (3, >= n); tag : ndarray, shape (>= n,)
        Work space.
    rest, code : ndarray, shape (>= n,), int64
        Output: the trials not in the star, in increasing order, and why: LEAVES_MESH, or -1
        (beyond the star).

    Returns
    -------
    int
        Number of trials in ``rest``.
    """
    for t in range(n):
        dl[0, t] = smax * _unit_disp(w, z, t, 0)
        dl[1, t] = smax * _unit_disp(w, z, t, 1)
        dl[2, t] = smax * _unit_disp(w, z, t, 2)
    d0s = dl[0]
    d1s = dl[1]
    d2s = dl[2]
    _deepest_cells(lmat.reshape((lmat.shape[0], 9)), n_star, d0s, d1s, d2s, n, tag)
    nf = 0
    for t in range(n):
        d0 = d0s[t]
        d1 = d1s[t]
        d2 = d2s[t]
        s = np.uint64(_bits_from_float(tag[t]) & _STAR_TAG)
        s = s if s < np.uint64(n_star) else np.uint64(0)  # unsigned: no index wrap-around
        l0, l1, l2 = _lam3(lmat, s, d0, d1, d2)
        inside = min(min(l0, l1), min(l2, 1.0 - (l0 + l1 + l2))) >= -BARY_EPS
        err[0, t], err[1, t], err[2, t] = _err3(dmat, s, l0, l1, l2)
        rest[nf] = t  # branch-free compaction of the trials still to place
        nf += not inside
    n_rest = 0
    for f in range(nf):
        t = rest[f]
        d0 = d0s[t]
        d1 = d1s[t]
        d2 = d2s[t]
        start = np.int64(_bits_from_float(tag[t]) & _STAR_TAG)
        s, l0, l1, l2 = star_locate3(start if start < n_star else 0, lmat, nbr, n_star,
                                     d0, d1, d2)  # fmt: skip
        if s >= 0:
            err[0, t], err[1, t], err[2, t] = _err3(dmat, s, l0, l1, l2)
        else:
            rest[n_rest] = t  # n_rest <= f: overwrites only entries already read
            code[n_rest] = s
            n_rest += 1
    return n_rest


@nb.njit(inline="always", **JIT)
def _taylor(grad, g, c, d0, d1, d2):
    """Component c of grad[g] . delta (d = 3): the first-order change of B at node g."""
    return 0.0 + grad[g, c, 0] * d0 + grad[g, c, 1] * d1 + grad[g, c, 2] * d2


@nb.njit(inline="always", **JIT)
def _abs_change(b0, e0, e1, e2, abs0):
    """|b0 + e| - |b0| without cancellation: (2 b0.e + |e|^2) / (|b0 + e| + |b0|)."""
    x0 = b0[0] + e0
    x1 = b0[1] + e1
    x2 = b0[2] + e2
    den = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2) + abs0
    if den == 0.0:
        return 0.0
    return (2.0 * (b0[0] * e0 + b0[1] * e1 + b0[2] * e2) + e0 * e0 + e1 * e1 + e2 * e2) / den


@nb.njit(**JIT)
def _node_gauss(
    g,
    gkey,
    coords,
    values,
    simplices,
    transform,
    neighbors,
    start_cells,
    basis,
    sigma_axes,
    scales,
    n_trials,
    skey,
    fkey,
    p,
    exit_grad,
    search,
    buffers,
    stats,
    n_out,
    n_lost,
):
    """All trials and statistics of node ``g`` (see `gauss_sweep`). ``buffers``: the per-thread
    work arrays of `_gauss_buffers`.

    With node gradients in ``exit_grad`` (see `gauss_sweep`), a trial that leaves the map takes
    the node's first-order Taylor expansion B_g + grad B_g . delta (counted in ``n_out`` all the
    same); one that leaves through a boundary face at the node is then linear in U_p and joins
    the in-star trials.

    Trials whose largest displacement stays in the node's star are located in the star tables
    (`build_star`; in 3-D by the block pass `star_errors3`); the field is affine there, so their
    component errors at every U_p are the largest U_p's scaled. They are stored once
    (comp[kmax]); the few trials that leave the star take the global walk at each U_p and are
    stored per U_p (comp[k], or the back of comp[kmax]).
    A trial whose star walk crosses a border face at g is outside at every U_p when that face
    is a supporting plane of the mesh (`star_exact`); on a non-convex mesh, where it may not
    be, `star_exit` places it: in a star cell, outside at every U_p (nearer to g than any other
    cell), or the global walk (`locate_exact`) at the U_p values where nothing proves it.
    Component statistics then merge the scaled in-star tails with the sorted out-of-star values
    (`_merged_stats`); |B| is not linear in U_p and gets its own sample per U_p.
    """
    (comp, absb, scratch, zbuf, okbuf, cells, lmat, dmat, nbr, htab, bin_start, work, dl, tag,
     rest, code, wmat, r_in, r_out, cand, free) = buffers  # fmt: skip
    excess, reach = search[0], search[1]
    d = coords.shape[1]
    n_up = scales.shape[0]
    kmax = 0
    for k in range(n_up):
        if scales[k] > scales[kmax]:
            kmax = k
    smax = scales[kmax]
    ratio = np.empty(n_up)
    for k in range(n_up):
        ratio[k] = scales[k] / smax if smax > 0 else 0.0
    disp = np.empty(d)
    delta = np.empty(d)
    lam = np.empty(d)
    pt = np.empty(d)
    bary = np.empty(d + 1)
    bi = np.empty(3)
    err = np.empty(3)
    b0 = values[g]
    abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
    key = trial_key(skey, gkey)  # one sequence per node: positions 4t, 4t + 1 serve trial t
    n_abs = np.zeros(n_up, dtype=np.int64)  # |B| samples per U_p
    m_out = np.zeros(n_up, dtype=np.int64)  # out-of-star component samples per U_p
    n_in = 0  # in-star trials (components stored at kmax)
    n_exit = 0  # of which extrapolated (left the map through a boundary face at the node)
    extrapolate = exit_grad.shape[0] > 0
    for k in range(n_up):
        n_out[k] = 0
        n_lost[k] = 0
    for k in range(n_up):
        if scales[k] == 0.0:  # no displacement: every error is exactly zero
            for c in range(4):
                for j in range(6):
                    stats[k, c, j] = 0.0
    if smax == 0.0:
        return False
    n_star = build_star(
        g, start_cells[g, 0], simplices, transform, neighbors, values, cells, lmat, dmat, nbr,
        htab,
    )  # fmt: skip
    if n_star > 0 and d != 3:  # per direction bin, a star cell to start walks from
        star_bin_starts(lmat, nbr, n_star, d, smax, bin_start)
    exact = star_exact(g, cells, n_star, simplices, excess)  # LEAVES_MESH is proven
    n_cand = 0
    n_free = 0
    if not exact:
        n_cand, n_free = star_behind(g, coords, cells, n_star, lmat, nbr, simplices, cand, free)
    normals_by_index(key, fkey, 0, n_trials, zbuf, okbuf)
    # place every trial in the star at the largest U_p; the others are listed in ``rest``
    for c in range(3):  # mesh-frame displacement per unit normal (projected for planar maps)
        for a in range(d):
            wmat[c, a] = basis[c, a] * sigma_axes[c]
    if d == 3 and n_star > 0:
        n_rest = star_errors3(zbuf, n_trials, wmat, smax, lmat, dmat, nbr, n_star, comp[kmax],
                              dl, tag, rest, code)  # fmt: skip
        kept = 0
        for r in range(n_rest):
            t = rest[r]
            r_in[kept] = 0.0
            r_out[kept] = np.inf
            if code[r] == LEAVES_MESH and not exact:  # no proof by itself at this node
                for a in range(3):
                    delta[a] = dl[a, t]
                s, r_in[kept], r_out[kept] = star_exit(lmat, reach[g], cand, n_cand, free,
                                                       n_free, delta, lam)  # fmt: skip
                if s == BEYOND_REACH:
                    s, r_in[kept], r_out[kept] = star_recheck(
                        g, cells, n_star, lmat, nbr, simplices, excess, reach[g], delta, lam
                    )
                if s >= 0:  # an in-star trial after all
                    comp[kmax, 0, t], comp[kmax, 1, t], comp[kmax, 2, t] = _err3(
                        dmat, s, lam[0], lam[1], lam[2]
                    )
                    continue
                code[r] = s
            rest[kept] = t  # kept <= r: overwrites only entries already read
            code[kept] = code[r]
            kept += 1
        n_rest = kept
        if extrapolate:  # exits at the node: the Taylor expansion, linear in U_p (in-star)
            kept = 0
            for r in range(n_rest):
                t = rest[r]
                if code[r] == LEAVES_MESH:
                    for c in range(3):
                        comp[kmax, c, t] = _taylor(exit_grad, g, c, dl[0, t], dl[1, t], dl[2, t])
                    n_exit += 1
                else:
                    rest[kept] = t  # kept <= r: overwrites only entries already read
                    code[kept] = code[r]
                    r_in[kept] = r_in[r]
                    r_out[kept] = r_out[r]
                    kept += 1
            n_rest = kept
        if n_rest > 0:  # in-star errors to the front, in trial order
            r = 0
            for t in range(n_trials):
                if r < n_rest and rest[r] == t:
                    r += 1
                    continue
                for c in range(3):
                    comp[kmax, c, n_in] = comp[kmax, c, t]
                n_in += 1
        else:
            n_in = n_trials
    else:
        n_rest = 0
        for t in range(n_trials):
            for a in range(d):
                delta[a] = smax * _unit_disp(wmat, zbuf, t, a)
            s = -1
            r_lo = 0.0
            r_hi = np.inf
            if n_star > 0:
                s = star_locate(bin_start[direction_bin(delta, d)], lmat, nbr, n_star, delta, lam)
                if s == LEAVES_MESH and not exact:  # no proof by itself at this node
                    s, r_lo, r_hi = star_exit(lmat, reach[g], cand, n_cand, free, n_free,
                                              delta, lam)  # fmt: skip
                    if s == BEYOND_REACH:
                        s, r_lo, r_hi = star_recheck(g, cells, n_star, lmat, nbr, simplices,
                                                     excess, reach[g], delta, lam)  # fmt: skip
            taylor = extrapolate and s == LEAVES_MESH  # linear in U_p, as an in-star trial
            if s >= 0 or taylor:
                mat, row, vec = (exit_grad, g, delta) if taylor else (dmat, s, lam)
                for c in range(3):
                    e = 0.0
                    for a in range(d):
                        e += mat[row, c, a] * vec[a]
                    comp[kmax, c, n_in] = e
                n_in += 1
                n_exit += taylor
            else:
                rest[n_rest] = t
                code[n_rest] = s
                r_in[n_rest] = r_lo
                r_out[n_rest] = r_hi
                n_rest += 1
    for r in range(n_rest):
        t = rest[r]
        if code[r] == LEAVES_MESH:  # outside the map at every U_p: counted, left out
            for k in range(n_up):
                if scales[k] > 0.0:
                    n_out[k] += 1
            continue
        # left the star: the global walk at each U_p (stored from the back of comp[kmax], so
        # |B| of in-star trials is filled in below)
        octant = 0
        for a in range(d):
            disp[a] = _unit_disp(wmat, zbuf, t, a)
            if disp[a] < 0.0:
                octant |= 1 << a
        start = start_cells[g, octant]
        cell = start
        for k in range(n_up):
            if scales[k] == 0.0:
                continue
            for a in range(d):
                pt[a] = coords[g, a] + scales[k] * disp[a]
            if ratio[k] < r_in[r] or ratio[k] > r_out[r]:  # proven (`star_recheck`)
                s = OUTSIDE
            else:
                s = locate_exact(pt, cell if cell >= 0 else start, transform, neighbors, bary,
                                 search)  # fmt: skip
                if s == WALK_FAILED:  # rare: a walk that cycled (non-Delaunay meshes only)
                    s = settle_walk(pt, transform, search, bary)
            if s == OUTSIDE:
                n_out[k] += 1
                if not extrapolate:
                    continue
                for c in range(3):  # the Taylor expansion at the node
                    e = 0.0
                    for a in range(d):
                        e += exit_grad[g, c, a] * (scales[k] * disp[a])
                    err[c] = e
            else:
                cell = s
                _interp_in(s, bary, simplices, values, bi)
                for c in range(3):
                    err[c] = bi[c] - b0[c]
            mk = m_out[k]
            col = n_trials - 1 - mk if k == kmax else mk
            for c in range(3):
                comp[k, c, col] = err[c]
            absb[k, n_trials - 1 - mk] = _abs_change(
                b0, err[0], err[1], err[2], abs0
            )  # from the back: the front takes the in-star trials below
            m_out[k] = mk + 1
    all_star = n_star > 0
    for k in range(n_up):
        if scales[k] > 0.0:
            n_out[k] += n_exit
        # with extrapolation every trial has a value: exits are in-star or in m_out
        if m_out[k] > 0 or (n_out[k] > 0 and not extrapolate):
            all_star = False
    # |B| per U_p: in-star trials at the front, out-of-star ones already at the back
    for k in range(n_up):
        if scales[k] == 0.0:
            continue
        r = ratio[k]
        for j in range(n_in):
            absb[k, j] = _abs_change(
                b0, r * comp[kmax, 0, j], r * comp[kmax, 1, j], r * comp[kmax, 2, j], abs0
            )
        mk = m_out[k]
        for j in range(mk):  # close the gap
            absb[k, n_in + j] = absb[k, n_trials - mk + j]
        n_abs[k] = n_in + mk
    # components
    if all_star:
        for c in range(3):
            sample_stats(comp[kmax, c], n_in, coverage_count(n_in, p), stats[kmax, c], scratch)
            for k in range(n_up):
                if k != kmax:
                    for j in range(6):
                        stats[k, c, j] = ratio[k] * stats[kmax, c, j]
    else:
        low = work[0]
        high = work[1]
        full = work[2]
        ybuf = work[3]
        for c in range(3):
            x = comp[kmax, c]
            # in-star sums and tails (the tails sorted, kept in scratch)
            shift, s1, s2, n_lo, n_hi = sums_and_tails(x, n_in, scratch, n_trials)
            if n_in < 2 or not s2 - s1 * s1 / n_in > 0.0:
                n_lo = 0  # degenerate: take the exact whole-sample path
                n_hi = 0
            lo_tail = scratch[:n_lo]
            hi_tail = scratch[n_trials - n_hi : n_trials]
            sort_values(lo_tail)
            sort_values(hi_tail)
            for k in range(n_up):
                if scales[k] == 0.0:
                    continue
                mk = m_out[k]
                for j in range(mk):
                    ybuf[j] = comp[k, c, n_trials - mk + j] if k == kmax else comp[k, c, j]
                sort_values(ybuf[:mk])
                _merged_stats(x, n_in, shift, s1, s2, lo_tail, hi_tail, ratio[k], ybuf, mk, p,
                              stats[k, c], low, high, full, work[4])  # fmt: skip
    for k in range(n_up):
        if scales[k] == 0.0:
            continue
        nk = n_abs[k]
        sample_stats(absb[k], nk, coverage_count(nk, p) if nk > 1 else 1, stats[k, 3], scratch)
    return all_star


@nb.njit(**JIT)
def _gauss_buffers(n_up, n_trials, d):
    """Per-thread work arrays of `_node_gauss`: samples (comp, absb, scratch), normals (zbuf,
    okbuf), star tables (cells, lmat, dmat, nbr, htab, bin_start), merge space (work) and the
    star pass's work space (dl, tag, rest, code, wmat; `star_errors3`) and, per trial in
    ``rest``, the fractions of its largest displacement where it is proven outside (r_in,
    r_out; `star_recheck`), and the star cells and free faces of `star_behind` (cand, free)."""
    return (
        np.empty((n_up, 3, n_trials)),
        np.empty((n_up, n_trials)),
        np.empty(n_trials),
        np.empty((3, n_trials)),
        np.empty(n_trials, dtype=np.bool_),
        np.empty(MAX_STAR, dtype=np.int64),
        np.empty((MAX_STAR, d, d)),
        np.empty((MAX_STAR, 3, d)),
        np.empty((MAX_STAR, d), dtype=np.int64),
        np.full((3, STAR_HASH), -1, dtype=np.int64),
        np.zeros((1 << d) * BIN_LEVELS ** (d - 1), dtype=np.int64),
        np.empty((5, n_trials)),
        np.empty((3, n_trials)),
        np.empty(n_trials),
        np.empty(n_trials, dtype=np.int64),
        np.empty(n_trials, dtype=np.int64),
        np.empty((3, d)),
        np.empty(n_trials),
        np.empty(n_trials),
        np.empty(MAX_STAR, dtype=np.int64),
        np.empty((2, MAX_STAR * d), dtype=np.int64),
    )


@nb.njit(**JIT)
def gauss_sweep(
    nodes,
    keys,
    coords,
    values,
    simplices,
    transform,
    neighbors,
    start_cells,
    basis,
    sigma_axes,
    scales,
    n_trials,
    seed,
    p,
    exit_grad,
    search,
):
    """Monte Carlo of B(x + N(0, U_p)) - B(x) at each node, statistics streamed per node.

    One thread: callers run blocks of nodes on several threads (`cfm_fem.threads`). A numba
    parallel loop here would recompile the whole kernel tree twice more on first use (~7 s).

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
        Node indices (rows of the arrays below) to process; results do not depend on how nodes
        are chunked.
    keys : ndarray, shape (k,), int64
        Random-stream id of each node (`cfm_fem.sweep.node_keys`): a node's numbers depend on
        its key only, so a part of a map held in its own arrays gives the whole map's numbers.
    coords : ndarray, shape (n, d), mm, mesh frame
    values : ndarray, shape (n, 3), T
    simplices, transform, neighbors : arrays of a `SimplexMesh`
    start_cells : ndarray, shape (n, 2**d), int64
        Walk start per node and octant of the displacement (`octant_cells`); -1 for nodes in
        no cell.
    basis : ndarray, shape (3, d)
        Map frame -> mesh frame (identity for 3-D).
    sigma_axes : ndarray, shape (3,)
        Per-axis multiplier of U_p (1, 1, 1 for isotropic).
    scales : ndarray, shape (n_up,), mm
        U_p values; trial t uses the same standard normals for every U_p (common random numbers).
    n_trials : int
    seed : int
    p : float
        Coverage probability (0.95).
    exit_grad : ndarray, shape (n, 3, d) or (0, 3, d), T/mm, mesh frame
        Empty: trials that leave the mesh are left out of the statistics. Else the node
        gradients (`cfm_fem.sweep.node_gradients` in the mesh frame): a trial that leaves takes
        the node's first-order Taylor expansion B_g + grad B_g . delta.
    search : tuple
        Face excess and cell buckets of the mesh (`locate_exact`;
        `cfm_fem.interpolation.exact_search`): whether a trial left the mesh is then exact on
        non-convex meshes too. Empty arrays for a convex mesh (its border faces are
        supporting planes, every exit is a proof).

    Returns
    -------
    stats : ndarray, shape (k, n_up, 4, 6), T
        Per node, U_p value, component (Bx, By, Bz, |B|) and statistic (`STAT_NAMES`) of the
        error B_meas - B_nom over the trials that stayed inside the mesh (all trials with
        ``exit_grad``).
    n_out : ndarray, shape (k, n_up), int64
        Trials whose perturbed point left the mesh (left out, or extrapolated).
    n_lost : ndarray, shape (k, n_up), int64
        Trials left without a value by a walk that did not end: 0, a walk that cycles is
        settled exactly (`settle_walk`); kept for the outputs' ``walk_failed_fraction``.
    star : ndarray, shape (k,), bool
        True if every trial stayed in a cell incident to the node (errors exactly linear in U_p).
    """
    k_nodes = nodes.shape[0]
    n_up = scales.shape[0]
    stats = np.full((k_nodes, n_up, 4, 6), np.nan)
    n_out = np.zeros((k_nodes, n_up), dtype=np.int64)
    n_lost = np.zeros((k_nodes, n_up), dtype=np.int64)
    star = np.zeros(k_nodes, dtype=np.bool_)
    skey = stream_key(seed, STREAM_SWEEP)
    fkey = stream_key(seed, STREAM_FALLBACK)
    buffers = _gauss_buffers(n_up, n_trials, coords.shape[1])
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:
            continue
        star[i] = _node_gauss(g, keys[i], coords, values, simplices, transform, neighbors,
                              start_cells, basis, sigma_axes, scales, n_trials, skey, fkey, p,
                              exit_grad, search, buffers, stats[i], n_out[i],
                              n_lost[i])  # fmt: skip
    return stats, n_out, n_lost, star


# =============================================================================================
# Coupled field Monte Carlo (issue 4; cfm_fem/coupled.py). Appended section: the probe position
# errors of a block of (trial, point) pairs with exactly the kinematics kernels above
# (`axis_noise_mm`, `probe_error_mm`), so the coupled model sees the same E_p samples as
# `cfm-fem kinematics` for the same (seed, trial, point index). Plain-numpy twin:
# `cfm_fem.kinematics.probe_errors_for_bench` with `point_noise` (tests/test_coupled.py).
# =============================================================================================
@nb.njit(**PJIT)
def coupled_probe_errors(
    params, t0, q_cmd, pidx, nkey, fkey, stack, mounts, tool, strokes, profiles, sig, speed,
    tau_code, tau_par, out,
):  # fmt: skip
    """Probe position errors E_p of trials t0..t0+m-1 at the given points, bench frame, mm.

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Error amplitudes of the trials (rows of ``kinematics.draw_error_sets``).
    t0 : int
        Trial index of ``params[0]`` (selects the noise stream of each trial).
    q_cmd : ndarray, shape (n, 3), mm
        Commanded axis positions.
    pidx : ndarray, shape (n,), int64
        Point index of each row of ``q_cmd`` in the noise stream (``axis_noise_mm``).
    nkey, fkey : uint64
        ``kinematics.noise_keys(seed)``.
    stack, mounts, tool, strokes, profiles, sig, speed, tau_code, tau_par
        ``kinematics.kernel_geometry(bench)`` fields.
    out : ndarray, shape (m, n, 3), mm
        Receives E_p = P_actual - P_nominal.
    """
    m = params.shape[0]
    n = q_cmd.shape[0]
    for t in nb.prange(m):
        dq = np.empty(3)
        e = np.empty(3)
        for i in range(n):
            axis_noise_mm(nkey, fkey, t0 + t, pidx[i], sig, speed, tau_code, tau_par, dq)
            probe_error_mm(params[t], q_cmd[i], dq, stack, mounts, tool, strokes, profiles, e)
            out[t, i, 0] = e[0]
            out[t, i, 1] = e[1]
            out[t, i, 2] = e[2]


# ---------------------------------------------------------------------------------------------
# Bench-model sweep (mode htm): probe errors from the 21-error HTM chain plus vibration/delay.
# ---------------------------------------------------------------------------------------------
@nb.njit(**JIT)
def htm_sweep(
    nodes, keys, coords, values, simplices, transform, neighbors, start_cells, basis, rot, q_nodes,
    params, terms, use_geometric, use_noise, nkey, fkey, sig, speed, tau_code, tau_par, stack,
    mounts, tool, strokes, profiles, p, exit_grad, search,
):  # fmt: skip
    """Monte Carlo of B(x + E_p) - B(x) with E_p from the bench model, statistics per node.

    Trial t uses error amplitudes ``params[t]`` for every node (a real bench has one set of
    geometric errors per scan) and the per-(trial, node) vibration and delay of
    `axis_noise_mm` (the node's key as the point index), so maps are reproducible from the seed.

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
    keys : ndarray, shape (k,), int64
        Noise-stream id of each node, as in `gauss_sweep`.
    coords, values, simplices, transform, neighbors, start_cells, basis :
        As in `gauss_sweep`.
    rot : ndarray, shape (3, 3)
        Bench frame -> map (magnet) frame.
    q_nodes : ndarray, shape (n, 3), mm
        Commanded axis positions that bring the probe to each node.
    params : ndarray, shape (T, 21)
        Error amplitudes per trial (`cfm_fem.kinematics.draw_error_sets`).
    terms : ndarray, shape (T, 21) or (1, 21) or (0, 21)
        When the bench's error profiles are constant: `trial_terms` of ``params`` (or of one
        row of zeros when ``use_geometric`` is False), and each sample costs the 18
        multiply-adds of the collapsed chain (`_chain`) instead of the 18 sines and cosines of
        `probe_error_mm`: the same probe error up to rounding. Empty: `probe_error_mm`.
    use_geometric, use_noise : bool
        Include the 21 geometric errors / the vibration and delay (to split the two parts).
    nkey, fkey, sig, speed, tau_code, tau_par :
        Noise model, as in `axis_noise_mm`.
    stack, mounts, tool, strokes, profiles :
        Bench geometry, as in `probe_error_mm`.
    p : float
        Coverage probability.
    exit_grad : ndarray, shape (n, 3, d) or (0, 3, d), T/mm
        As in `gauss_sweep`: trials that leave the mesh left out (empty) or given the node's
        first-order Taylor expansion; counted in ``n_out`` either way.
    search : tuple
        As in `gauss_sweep`. A trial that leaves the mesh where that is no proof is placed by
        `star_find` when nearer to its node than any other cell (`node_reach`), else by
        `locate_exact`.

    Returns
    -------
    stats : ndarray, shape (k, 1, 4, 6), T
    n_out, n_lost : ndarray, shape (k, 1), int64
        As `gauss_sweep` (n_lost: 0, failed walks are settled by `settle_walk`).
    pos : ndarray, shape (k, 3, 3)
        Over all trials, per map axis: mean (row 0, mm) and standard deviation (row 1, mm) of
        the probe error, and (row 2) its correlation coefficients xy, xz, yz (0 where an
        axis does not vary): the linearised (GUM) figure needs the covariance, as the
        geometric errors move the probe along several axes at once.
    """
    k_nodes = nodes.shape[0]
    n_trials = params.shape[0]
    d = coords.shape[1]
    stats = np.full((k_nodes, 1, 4, 6), np.nan)
    n_out = np.zeros((k_nodes, 1), dtype=np.int64)
    n_lost = np.zeros((k_nodes, 1), dtype=np.int64)
    pos = np.full((k_nodes, 3, 3), np.nan)
    zero = np.zeros(params.shape[1])
    comp = np.empty((3, n_trials))
    absb = np.empty(n_trials)
    scratch = np.empty(n_trials)
    dq = np.zeros(3)
    e = np.empty(3)
    dm = np.empty(3)
    bi = np.empty(3)
    # per node, all trials at once: the noise by the block generator (`axis_noise_mm`'s
    # numbers), then the probe points, then their walks (`walk_block3` in 3-D)
    tkeys = np.empty(n_trials, dtype=np.uint64)
    for t in range(n_trials):
        tkeys[t] = trial_key(nkey, t)
    z = np.zeros((3, n_trials))
    ok = np.empty(n_trials, dtype=np.bool_)
    pts = np.empty((n_trials, d))
    starts = np.empty(n_trials, dtype=np.int64)
    cells = np.empty(n_trials, dtype=np.int64)
    act = np.empty(n_trials, dtype=np.int64)
    bary = np.empty((n_trials, d + 1))
    excess, reach = search[0], search[1]
    scells = np.empty(MAX_STAR, dtype=np.int64)  # star tables (`build_star`), non-convex mesh
    lmat = np.empty((MAX_STAR, d, d))
    dmat = np.empty((MAX_STAR, 3, d))
    nbr = np.empty((MAX_STAR, d), dtype=np.int64)
    htab = np.full((3, STAR_HASH), -1, dtype=np.int64)
    delta = np.empty(d)
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:
            continue
        b0 = values[g]
        abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
        gk = keys[i]
        if use_noise:
            normals_by_key(tkeys, fkey, gk, n_trials, z, ok)
        s1 = np.zeros(3)
        s2 = np.zeros(3)
        sx = np.zeros(3)  # cross sums xy, xz, yz
        qg = q_nodes[g]
        for t in range(n_trials):
            for a in range(3):
                dq[a] = sig[a] * z[a, t]
            if use_noise and tau_code >= 0:  # eq. 9 delay, as in axis_noise_mm
                tau = _delay_tau(tkeys[t], gk, tau_code, tau_par)
                for a in range(3):
                    dq[a] += speed[a] * tau
            if terms.shape[0] > 0:
                tt = t if use_geometric else 0
                e[0], e[1], e[2], _norm = _chain(
                    terms, tt, qg[0], qg[1], qg[2], dq[0], dq[1], dq[2]
                )
            else:
                prm = params[t] if use_geometric else zero
                probe_error_mm(prm, qg, dq, stack, mounts, tool, strokes, profiles, e)
            octant = 0
            for a in range(3):
                dm[a] = rot[a, 0] * e[0] + rot[a, 1] * e[1] + rot[a, 2] * e[2]
                s1[a] += dm[a]
                s2[a] += dm[a] * dm[a]
            sx[0] += dm[0] * dm[1]
            sx[1] += dm[0] * dm[2]
            sx[2] += dm[1] * dm[2]
            for a in range(d):
                acc = 0.0
                for c in range(3):
                    acc += basis[c, a] * dm[c]
                pts[t, a] = coords[g, a] + acc
                if acc < 0.0:
                    octant |= 1 << a
            starts[t] = start_cells[g, octant]
        if d == 3:
            walk_block3(pts, 0, n_trials, starts, transform, neighbors, cells, act, bary)
        else:
            for t in range(n_trials):
                cells[t] = locate(pts[t], starts[t], transform, neighbors, bary[t])
        if excess.shape[0] > 0:  # non-convex mesh: is an exit a proof?
            n_star = -2  # the star of g, built at the first exit near g
            for t in range(n_trials):
                if cells[t] != OUTSIDE:
                    continue
                n2 = 0.0
                for a in range(d):
                    n2 += (pts[t, a] - coords[g, a]) ** 2
                if n2 < reach[g] ** 2:  # nearer to g than any other cell: in its star or out
                    if n_star == -2:
                        n_star = build_star(g, start_cells[g, 0], simplices, transform, neighbors,
                                            values, scells, lmat, dmat, nbr, htab)  # fmt: skip
                    if n_star > 0:
                        cells[t] = star_find(pts[t], g, coords, transform, scells, n_star, lmat,
                                             delta, bary[t])  # fmt: skip
                        continue
                cells[t] = locate_exact(pts[t], starts[t], transform, neighbors, bary[t], search)
        nv = 0
        for t in range(n_trials):
            s = cells[t]
            if s == WALK_FAILED:  # rare: a walk that cycled (non-Delaunay meshes only)
                s = settle_walk(pts[t], transform, search, bary[t])
            if s == OUTSIDE:
                n_out[i, 0] += 1
                if exit_grad.shape[0] == 0:
                    continue
                for c in range(3):  # the Taylor expansion at the node
                    e0 = 0.0
                    for a in range(d):
                        e0 += exit_grad[g, c, a] * (pts[t, a] - coords[g, a])
                    comp[c, nv] = e0
            else:
                _interp_in(s, bary[t], simplices, values, bi)
                for c in range(3):
                    comp[c, nv] = bi[c] - b0[c]
            absb[nv] = _abs_change(b0, comp[0, nv], comp[1, nv], comp[2, nv], abs0)
            nv += 1
        bessel = n_trials / max(n_trials - 1, 1)
        for a in range(3):
            mean = s1[a] / n_trials
            pos[i, 0, a] = mean
            pos[i, 1, a] = np.sqrt(max(s2[a] / n_trials - mean * mean, 0.0) * bessel)
        for j in range(3):
            a, b = (0, 0, 1)[j], (1, 2, 2)[j]
            sd = pos[i, 1, a] * pos[i, 1, b]
            cov = (sx[j] / n_trials - pos[i, 0, a] * pos[i, 0, b]) * bessel
            pos[i, 2, j] = min(max(cov / sd, -1.0), 1.0) if sd > 0.0 else 0.0
        q = coverage_count(nv, p) if nv > 1 else 1
        for c in range(3):
            sample_stats(comp[c], nv, q, stats[i, 0, c], scratch)
        sample_stats(absb, nv, q, stats[i, 0, 3], scratch)
    return stats, n_out, n_lost, pos
