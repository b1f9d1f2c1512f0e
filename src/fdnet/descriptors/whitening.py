"""PCA whitening of global descriptors, the classical retrieval post-processing.

Source: H. Jégou and O. Chum, "Negative evidences and co-occurrences in image retrieval: the
benefit of PCA and whitening", ECCV 2012. Vectors are L2-normalised, centred on the mean of a
fitting set, projected on its first ``L`` principal directions, each coordinate divided by the
square root of its eigenvalue (so every kept direction has unit variance: frequent, co-occurring
patterns no longer dominate the cosine), and L2-normalised again. Learnt without labels, from any
images of the kind to be matched.

``power`` (default 1) softens the whitening: coordinate ``k`` is divided by
``eigenvalue_k ** (power / 2)``; 1 is full whitening, 0 is a plain PCA projection, values between
shrink the weight of the weak directions less than full whitening does (useful when the fitting
set is small and the last kept eigenvalues are noisy).

Pure numpy (no torch), so any method, FDNet's head included, can start from it.
"""

from __future__ import annotations

import numpy as np

from fdnet.errors import ConfigError, DataError

#: eigenvalues below this fraction of the largest are treated as zero (duplicate or constant
#: fitting vectors): dividing by their square root would blow noise up to unit variance
RELATIVE_EIGENVALUE_FLOOR = 1e-10


def _l2(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.maximum(norm, 1e-12)


def max_whitening_dim(num_vectors: int, dim: int) -> int:
    """The largest L a fitting set of ``num_vectors`` vectors of length ``dim`` allows: centred
    vectors span at most ``num_vectors - 1`` directions, and there are only ``dim`` of them."""
    return max(0, min(int(num_vectors) - 1, int(dim)))


def principal_directions(x: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred (N, D) vectors -> (components (dim, D), orthonormal rows by decreasing variance; the
    variances along them (dim,)). Also the start of FDNet's projection head
    (:mod:`fdnet.methods.fdnet.content_fit`).

    The eigen-decomposition of the smaller of the Gram (N x N) and covariance (D x D) matrices.
    Written here rather than sklearn's PCA because with N << D (a few thousand images,
    10^4-dimensional maps) its exact solver runs a full SVD, several times slower than one matrix
    product and an N x N eigh; its randomized one is approximate."""
    n, d = x.shape
    if n <= d:
        values, vectors_n = np.linalg.eigh(x @ x.T)
        order = np.argsort(values)[::-1][:dim]
        singular = np.sqrt(np.maximum(values[order], 0.0))
        components = ((x.T @ vectors_n[:, order]) / np.maximum(singular, 1e-300)).T
    else:
        values, vectors_d = np.linalg.eigh(x.T @ x)
        order = np.argsort(values)[::-1][:dim]
        components = vectors_d[:, order].T
    return components, values[order] / max(n - 1, 1)


class PCAWhitening:
    """A fitted whitening: ``transform`` maps (N, D) vectors to (N, L) unit vectors.

    Attributes (numpy, float32): ``mean`` (D,), ``components`` (L, D, orthonormal rows, by
    decreasing eigenvalue), ``eigenvalues`` (L,), and ``power``.
    """

    def __init__(self, mean: np.ndarray, components: np.ndarray, eigenvalues: np.ndarray, power: float = 1.0) -> None:
        self.mean = np.asarray(mean, dtype=np.float32)
        self.components = np.asarray(components, dtype=np.float32)
        self.eigenvalues = np.asarray(eigenvalues, dtype=np.float32)
        self.power = float(power)
        # dividing by eigenvalue^(power/2) is a per-column scale of the projection: folded in once
        self._projection = (self.components.T / self.eigenvalues ** (self.power / 2)).astype(np.float32)

    @property
    def dim(self) -> int:
        return int(self.components.shape[0])

    @property
    def input_dim(self) -> int:
        return int(self.components.shape[1])

    @classmethod
    def fit(cls, vectors: np.ndarray, dim: int, power: float = 1.0, where: str = "whitening") -> "PCAWhitening":
        """Learn the whitening to ``dim`` dimensions from (N, D) ``vectors`` (any scale: they are
        L2-normalised first). ``where`` names the setting in error messages.

        Raises ConfigError when ``dim`` is not in 1..min(N - 1, D) and DataError when the vectors
        span fewer than ``dim`` directions (duplicates).
        """
        x = np.asarray(vectors, dtype=np.float64)
        if x.ndim != 2:
            raise DataError(f"{where}: expected an (N, D) array of vectors, got shape {x.shape}")
        n, d = x.shape
        dim = int(dim)
        power = float(power)
        if not np.isfinite(power) or power < 0:
            raise ConfigError(
                f"{where}: power must be a number >= 0 (1 = full whitening, 0 = PCA only), " f"got {power}"
            )
        limit = max_whitening_dim(n, d)
        if dim < 1 or dim > limit:
            raise ConfigError(
                f"{where}: L = {dim} dimensions, but {n} fitting vectors of length {d} allow "
                f"1..{limit} (at most one fewer than the fitting images, at most the map's "
                f"length); lower L or fit on more images"
            )
        if not np.isfinite(x).all():
            raise DataError(f"{where}: the fitting vectors contain NaN or infinite values")
        x = _l2(x)
        mean = x.mean(axis=0)
        x -= mean
        components, eigenvalues = principal_directions(x, dim)
        top = float(eigenvalues[0]) if len(eigenvalues) else 0.0
        spanned = int(np.sum(eigenvalues > RELATIVE_EIGENVALUE_FLOOR * max(top, 1e-300))) if top > 0 else 0
        if spanned < dim:
            raise DataError(
                f"{where}: the {n} fitting vectors span only {spanned} directions (duplicate or "
                f"constant images?), fewer than L = {dim}; lower L or fit on more varied images"
            )
        # A fixed sign per direction (largest-magnitude coordinate positive): the decomposition's
        # sign is arbitrary, and a deterministic one keeps fingerprints stable across machines.
        signs = np.sign(components[np.arange(dim), np.argmax(np.abs(components), axis=1)])
        components *= np.where(signs == 0, 1.0, signs)[:, None]
        return cls(mean, components, eigenvalues, power)

    def transform(self, vectors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, L) float32 unit vectors: L2-normalise, centre, project, scale, L2-normalise."""
        x = np.asarray(vectors, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.input_dim:
            raise DataError(f"whitening: expected vectors of length {self.input_dim}, got shape {x.shape}")
        return _l2(((_l2(x) - self.mean) @ self._projection).astype(np.float32)).astype(np.float32)

    def settings(self) -> dict:
        return {"dim": self.dim, "input_dim": self.input_dim, "power": self.power}
