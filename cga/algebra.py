"""The conformal geometric algebra G(4,1) as a table-driven numpy kernel.

Basis vectors, in this order: e1, e2, e3, e+ (e+^2 = +1), e- (e-^2 = -1).  A multivector is
a dense array of 32 coefficients over the basis blades, ordered by grade and then
lexicographically (1; e1 .. e-; e12 .. e+-; ...; e123+-).  ``Multivector`` wraps an array of
shape (..., 32): the leading axes are a batch, and every operation broadcasts over them
without a Python loop over the batch.

Products are computed from precomputed (i, j) -> (k, sign) tables restricted to the
components that are non-zero somewhere in the operands, so the sparse entities of CGA (points:
5 components, motors: 12) cost what their sparsity says rather than 32 x 32.
"""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations

import numpy as np

NAMES = ("1", "2", "3", "+", "-")
METRIC = np.array([1.0, 1.0, 1.0, 1.0, -1.0])
DIM = 5
N = 32

# Blades as bit masks (bit i = basis vector i), sorted by grade then lexicographically.
BLADES: tuple[int, ...] = tuple(
    sum(1 << i for i in combo) for g in range(DIM + 1) for combo in combinations(range(DIM), g)
)
INDEX = {mask: pos for pos, mask in enumerate(BLADES)}
GRADE = np.array([bin(m).count("1") for m in BLADES])
BLADE_NAMES = tuple(
    "1" if m == 0 else "e" + "".join(NAMES[i] for i in range(DIM) if m >> i & 1) for m in BLADES
)


def _reorder_sign(a: int, b: int) -> int:
    """Sign from sorting the basis vectors of blade a followed by blade b into canonical order."""
    a >>= 1
    swaps = 0
    while a:
        swaps += bin(a & b).count("1")
        a >>= 1
    return -1 if swaps & 1 else 1


def _blade_product(a: int, b: int) -> tuple[int, float]:
    sign = float(_reorder_sign(a, b))
    common = a & b
    for i in range(DIM):
        if common >> i & 1:
            sign *= METRIC[i]
    return a ^ b, sign


# GP[i, j] = sign, PROD_INDEX[i, j] = k for the geometric product of blades i and j.
PROD_INDEX = np.zeros((N, N), dtype=np.intp)
GP = np.zeros((N, N))
for _i, _a in enumerate(BLADES):
    for _j, _b in enumerate(BLADES):
        _m, _s = _blade_product(_a, _b)
        PROD_INDEX[_i, _j] = INDEX[_m]
        GP[_i, _j] = _s
_GA = GRADE[:, None]
_GB = GRADE[None, :]
_GK = GRADE[PROD_INDEX]
# Outer product: grade adds.  Left contraction: grade(a) <= grade(b), result grade difference.
OP = np.where(_GK == _GA + _GB, GP, 0.0)
LC = np.where((_GK == _GB - _GA) & (_GA <= _GB), GP, 0.0)
# Scalar product table (used for norms): only terms landing on the scalar.
REVERSE_SIGN = np.where((GRADE * (GRADE - 1) // 2) % 2 == 1, -1.0, 1.0)
INVOLUTION_SIGN = np.where(GRADE % 2 == 1, -1.0, 1.0)
GRADE_MASK = {k: (GRADE == k).tobytes() for k in range(DIM + 1)}
_TABLES = {"gp": GP, "op": OP, "lc": LC}
_CHUNK = 512  # batch rows per block in the pairwise kernel (bounds temporary memory)


@lru_cache(maxsize=512)
def _pairs(kind: str, act_a: bytes, act_b: bytes):
    """Active components ia, ib, the output blades ko the product can reach from them, and
    the (len(ia)*len(ib), len(ko)) matrix T with
    (a op b)[ko_k] = sum_(i,j) a[ia_i] b[ib_j] T[i*len(ib)+j, k]."""
    table = _TABLES[kind]
    ia = np.flatnonzero(np.frombuffer(act_a, dtype=bool))
    ib = np.flatnonzero(np.frombuffer(act_b, dtype=bool))
    T = np.zeros((ia.size, ib.size, N))
    I, J = np.meshgrid(np.arange(ia.size), np.arange(ib.size), indexing="ij")
    T[I, J, PROD_INDEX[ia[I], ib[J]]] = table[ia[I], ib[J]]
    T = T.reshape(ia.size * ib.size, N)
    reach = np.any(T != 0, axis=0)
    ko = np.flatnonzero(reach)
    return ia, ib, ko, T[:, ko], reach.tobytes()


def _active(x: np.ndarray) -> bytes:
    """Components that are non-zero anywhere in the batch (a scan of the data)."""
    flat = x.reshape(-1, N)
    return np.any(flat != 0, axis=0).tobytes()


def product(kind: str, a: np.ndarray, b: np.ndarray, act_a: bytes | None = None,
            act_b: bytes | None = None) -> tuple[np.ndarray, bytes]:
    """Bilinear product of coefficient arrays (..., 32) x (..., 32) -> (..., 32).

    ``kind`` is 'gp' (geometric), 'op' (outer) or 'lc' (left contraction).  ``act_a`` and
    ``act_b`` are optional masks of the components that may be non-zero (known from how the
    operands were built); without them the data is scanned.  Returns the product and the mask
    of components it can reach.  A single operand against a batch becomes one matrix product;
    two batches go through the outer product of their active components times the product
    table, in blocks of rows (BLAS does the sums).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ia, ib, ko, T, reach = _pairs(kind, act_a or _active(a), act_b or _active(b))
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    out = np.zeros(shape + (N,))
    if ko.size == 0:
        return out, reach
    T3 = T.reshape(ia.size, ib.size, ko.size)
    if a.ndim == 1 and b.ndim > 1:
        out[..., ko] = b[..., ib] @ np.einsum("i,ijk->jk", a[ia], T3)
        return out, reach
    if b.ndim == 1 and a.ndim > 1:
        out[..., ko] = a[..., ia] @ np.einsum("j,ijk->ik", b[ib], T3)
        return out, reach
    a2 = np.broadcast_to(a, shape + (N,)).reshape(-1, N)[:, ia]
    b2 = np.broadcast_to(b, shape + (N,)).reshape(-1, N)[:, ib]
    flat = out.reshape(-1, N)
    for lo in range(0, a2.shape[0], _CHUNK):
        hi = lo + _CHUNK
        outer = (a2[lo:hi, :, None] * b2[lo:hi, None, :]).reshape(-1, ia.size * ib.size)
        flat[lo:hi, ko] = outer @ T
    return out, reach


class Multivector:
    """A (batch of) multivector(s) of G(4,1): coefficients in ``self.v`` with shape (..., 32).

    Operators: ``*`` geometric product (or scaling by a number), ``^`` outer product,
    ``|`` left contraction, ``~x`` reverse, ``+``/``-``.  In Python ``^`` and ``|`` bind more
    loosely than ``+`` and ``*``: parenthesise.
    """

    __slots__ = ("v", "active")
    __array_priority__ = 100  # numpy scalars on the left defer to our operators

    def __init__(self, coeffs, active: bytes | None = None):
        v = np.asarray(coeffs, dtype=float)
        if v.shape[-1:] != (N,):
            raise ValueError(f"a G(4,1) multivector needs 32 coefficients, got shape {v.shape}")
        self.v = v
        # Mask (32 bools as bytes) of the components that may be non-zero, when known from
        # construction; products use it instead of scanning a large batch.
        self.active = active

    # construction -------------------------------------------------------------------------
    @classmethod
    def scalar(cls, s) -> Multivector:
        s = np.asarray(s, dtype=float)
        v = np.zeros(s.shape + (N,))
        v[..., 0] = s
        return cls(v)

    @classmethod
    def from_vector(cls, x) -> Multivector:
        """Grade-1 multivector(s) from (..., 5) coefficients on e1, e2, e3, e+, e-."""
        x = np.asarray(x, dtype=float)
        v = np.zeros(x.shape[:-1] + (N,))
        v[..., 1:6] = x
        return cls(v, GRADE_MASK[1])

    @classmethod
    def stack(cls, items) -> Multivector:
        return cls(np.stack([m.v for m in items]))

    # container behaviour ------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, ...]:
        return self.v.shape[:-1]

    def __len__(self) -> int:
        if self.v.ndim == 1:
            raise TypeError("a single multivector has no length")
        return self.v.shape[0]

    def __getitem__(self, idx) -> Multivector:
        if not isinstance(idx, tuple):
            idx = (idx,)
        return Multivector(self.v[idx + (slice(None),)], self.active)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __getattr__(self, name: str):
        # Coefficient access by blade name, e.g. X.e12, X.e1p (p: e+, m: e-).
        if name.startswith("e") and len(name) > 1:
            key = "e" + name[1:].replace("p", "+").replace("m", "-")
            if key in BLADE_NAMES:
                return self.v[..., BLADE_NAMES.index(key)]
        raise AttributeError(name)

    # arithmetic ---------------------------------------------------------------------------
    @staticmethod
    def _coerce(other) -> np.ndarray | None:
        if isinstance(other, Multivector):
            return other.v
        if np.isscalar(other) or (isinstance(other, np.ndarray) and other.ndim == 0):
            return None
        raise TypeError(f"cannot combine a Multivector with {type(other).__name__}")

    def __add__(self, other) -> Multivector:
        o = self._coerce(other)
        if o is None:
            v = self.v.copy()
            v[..., 0] += other
            return Multivector(v)
        return Multivector(self.v + o)

    __radd__ = __add__

    def __neg__(self) -> Multivector:
        return Multivector(-self.v, self.active)

    def __sub__(self, other) -> Multivector:
        return self + (-other)

    def __rsub__(self, other) -> Multivector:
        return (-self) + other

    def _product(self, kind: str, other: Multivector) -> Multivector:
        return Multivector(*product(kind, self.v, other.v, self.active, other.active))

    def __mul__(self, other) -> Multivector:
        o = self._coerce(other)
        if o is None:
            return Multivector(self.v * other, self.active)
        return self._product("gp", other)

    def __rmul__(self, other) -> Multivector:
        return Multivector(self.v * other, self.active)

    def __truediv__(self, other) -> Multivector:
        if isinstance(other, Multivector):
            return self * other.inverse()
        other = np.asarray(other, dtype=float)
        return Multivector(self.v / other[..., None] if other.ndim else self.v / other)

    def __xor__(self, other) -> Multivector:
        o = self._coerce(other)
        if o is None:
            return Multivector(self.v * other, self.active)
        return self._product("op", other)

    def __rxor__(self, other) -> Multivector:
        return Multivector(self.v * other)

    def __or__(self, other) -> Multivector:
        o = self._coerce(other)
        if o is None:
            return Multivector(self.v * other, self.active)  # contraction by a scalar
        return self._product("lc", other)

    def __invert__(self) -> Multivector:
        return self.reverse()

    # unary operations ---------------------------------------------------------------------
    def reverse(self) -> Multivector:
        return Multivector(self.v * REVERSE_SIGN, self.active)

    def involute(self) -> Multivector:
        return Multivector(self.v * INVOLUTION_SIGN, self.active)

    def grade(self, k: int) -> Multivector:
        mask = GRADE_MASK.get(k, bytes(N))
        if self.active is not None:
            mask = bytes(x & y for x, y in zip(mask, self.active, strict=True))
        return Multivector(np.where(GRADE == k, self.v, 0.0), mask)

    def grades(self, tol: float = 1e-12) -> set[int]:
        """Grades with a coefficient above ``tol`` anywhere in the batch."""
        big = np.any(np.abs(self.v.reshape(-1, N)) > tol, axis=0)
        return {int(g) for g in GRADE[big]}

    def scalar_part(self) -> np.ndarray:
        return self.v[..., 0]

    def vector_part(self) -> np.ndarray:
        """The (..., 5) grade-1 coefficients on e1, e2, e3, e+, e-."""
        return self.v[..., 1:6]

    def dual(self) -> Multivector:
        """X* = X I^-1 (so IPNS <-> OPNS); ``undual`` inverts it."""
        return self * I_INV

    def undual(self) -> Multivector:
        return self * I

    def sq_norm(self) -> np.ndarray:
        """<X ~X>_0: the signed squared norm (zero for null vectors such as points)."""
        return np.einsum("...k,k->...", self.v * self.v, _SCALAR_OF_X_REVX)

    def norm(self) -> np.ndarray:
        """sqrt(|<X ~X>_0|)."""
        return np.sqrt(np.abs(self.sq_norm()))

    def inverse(self) -> Multivector:
        """X^-1 with X X^-1 = 1.

        Versors and blades (X ~X a scalar) use ~X / (X ~X); anything else solves the
        32 x 32 linear system of left multiplication, batched.
        """
        xr = self * self.reverse()
        scal = xr.v[..., 0]
        rest = np.abs(xr.v[..., 1:]).max(axis=-1)
        if np.all(rest <= 1e-10 * np.maximum(1.0, np.abs(scal))) and np.all(scal != 0):
            return Multivector(self.reverse().v / scal[..., None])
        # L[..., k, j]: coefficient k of X * e_j, so X * Y = L @ y.
        flat = self.v.reshape(-1, N)
        L = np.zeros((flat.shape[0], N, N))
        L[:, PROD_INDEX, np.arange(N)[None, :]] = flat[:, :, None] * GP
        rhs = np.zeros((flat.shape[0], N, 1))
        rhs[:, 0, 0] = 1.0
        try:
            y = np.linalg.solve(L, rhs)[..., 0]
        except np.linalg.LinAlgError as exc:
            raise ZeroDivisionError("multivector is not invertible") from exc
        return Multivector(y.reshape(self.v.shape))

    def normalized(self) -> Multivector:
        n = self.norm()
        return Multivector(self.v / np.where(n == 0, 1.0, n)[..., None])

    # comparison and display ---------------------------------------------------------------
    def allclose(self, other, atol: float = 1e-9) -> bool:
        o = other.v if isinstance(other, Multivector) else Multivector.scalar(other).v
        return bool(np.allclose(self.v, o, atol=atol))

    def __repr__(self) -> str:
        if self.v.ndim > 1:
            return f"Multivector(batch shape {self.shape})"
        pairs = zip(self.v, BLADE_NAMES, strict=True)
        terms = [f"{c:+.6g}{'' if n == '1' else '*' + n}" for c, n in pairs if abs(c) > 1e-12]
        return "Multivector(" + (" ".join(terms) if terms else "0") + ")"


# <X ~X>_0 = sum_k x_k^2 * (sign of e_k ~e_k); e_k ~e_k is the product of the metric entries.
_SCALAR_OF_X_REVX = np.array(
    [np.prod([METRIC[i] for i in range(DIM) if m >> i & 1]) if m else 1.0 for m in BLADES]
)


def _basis(mask: int) -> Multivector:
    v = np.zeros(N)
    v[INDEX[mask]] = 1.0
    return Multivector(v)


e1 = _basis(0b00001)
e2 = _basis(0b00010)
e3 = _basis(0b00100)
ep = _basis(0b01000)
em = _basis(0b10000)
e0 = 0.5 * (em - ep)
einf = em + ep
I = _basis(0b11111)
I_INV = I.inverse()


def blade_index(name: str) -> int:
    """Position of a blade by name, e.g. 'e12', 'e3+-' ('p'/'m' accepted for '+'/'-')."""
    return BLADE_NAMES.index(name.replace("p", "+").replace("m", "-"))
