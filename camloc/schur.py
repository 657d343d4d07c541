"""Sparse symmetric positive definite solves for the smoother: poses, and landmarks eliminated by
their Schur complement.

The smoother's normal matrix, unknowns ordered poses (6 each) then landmarks (3 each), is

    H = [[Hpp, Hpl],          Hll block-diagonal: a landmark is tied only to the poses that see
         [Hlp, Hll]]          it and to its own map prior, never to another landmark.

so each landmark's 3x3 block is eliminated exactly (Triggs et al., "Bundle adjustment - a modern
synthesis", 2000, sec. 6.1; GTSAM and g2o do the same):

    S = Hpp - Hpl Hll^-1 Hlp             the reduced pose system, sparse (poses that share a
                                         landmark are coupled), factored once
    S xp = bp - Hpl Hll^-1 bl            the poses' step
    xl = Hll^-1 (bl - Hlp xp)            each landmark's step, 3x3 at a time

and the landmarks' marginal covariances are the diagonal blocks of H^-1,

    (H^-1)_ll = Hll^-1 + Hll^-1 Hlp S^-1 Hpl Hll^-1,

computed from the factor of S by selected inversion (``camloc.selected_inverse``), never from a
dense inverse of H. The factor is a sparse Cholesky, CHOLMOD's supernodal one
(``camloc.cholesky``: an approximate minimum degree ordering of S, dense BLAS blocks), for poses
alone as for the reduced system.

Pure: no I/O, no printing.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from camloc.cholesky import Cholesky

LANDMARK_DOF = 3
# Right-hand sides solved at once for the covariances where selected inversion cannot run: a dense
# (unknowns, 256) block, about 250 MB at 20,000 poses.
_COVARIANCE_BLOCK = 256


def factor(H: sp.spmatrix) -> Cholesky:
    """The sparse Cholesky factor of a symmetric positive definite H (``camloc.cholesky``).

    Raises
    ------
    np.linalg.LinAlgError : H is not positive definite.
    """
    return Cholesky(H)


def landmark_blocks(H: sp.spmatrix, first: int) -> np.ndarray:
    """The 3x3 diagonal blocks (L, 3, 3) of H's rows and columns from ``first`` on (landmarks)."""
    lower = sp.coo_matrix(H[first:, first:])
    count = lower.shape[0] // LANDMARK_DOF
    blocks = np.zeros((count, LANDMARK_DOF, LANDMARK_DOF))
    same = lower.row // LANDMARK_DOF == lower.col // LANDMARK_DOF
    np.add.at(blocks, (lower.row[same] // LANDMARK_DOF, lower.row[same] % LANDMARK_DOF,
                       lower.col[same] % LANDMARK_DOF), lower.data[same])
    return blocks


def inverse_blocks(blocks: np.ndarray) -> np.ndarray:
    """Inverses (L, 3, 3) of symmetric positive definite 3x3 blocks, through their Cholesky factors.

    Raises
    ------
    np.linalg.LinAlgError : a block that is not positive definite (its landmark is undetermined).
    """
    L = np.linalg.cholesky(blocks)
    L_inv = np.linalg.solve(L, np.broadcast_to(np.eye(LANDMARK_DOF), blocks.shape))
    return np.swapaxes(L_inv, 1, 2) @ L_inv  # H^-1 = L^-T L^-1


def block_diagonal(blocks: np.ndarray) -> sp.csr_matrix:
    """The sparse block-diagonal matrix of (L, 3, 3) blocks."""
    count = blocks.shape[0]
    return sp.bsr_matrix((blocks, np.arange(count), np.arange(count + 1)),
                         shape=(LANDMARK_DOF * count,) * 2).tocsr()


class SchurSolver:
    """Solves with a symmetric positive definite ``H`` whose unknowns from ``num_pose`` on are
    landmarks (3 each, tied only to poses and to themselves), after eliminating them.

    Parameters
    ----------
    H : (n, n) the normal matrix (the smoother's Jacobi-scaled one).
    num_pose : unknowns of the poses (6 (N - 1)); the rest are landmarks.
    damping : added to the whole diagonal (Levenberg-Marquardt on a unit-diagonal matrix).

    Raises
    ------
    np.linalg.LinAlgError : a landmark block, or the reduced pose system, that is not positive
        definite.
    """

    def __init__(self, H: sp.csc_matrix, num_pose: int, damping: float = 0.0) -> None:
        self.num_pose = num_pose
        blocks = landmark_blocks(H, num_pose) + damping * np.eye(LANDMARK_DOF)
        self.landmark_inverse = inverse_blocks(blocks)  # Hll^-1, (L, 3, 3)
        self.H_pl = sp.csr_matrix(H[:num_pose, num_pose:])
        # W = Hpl Hll^-1: every landmark's columns scaled by its own block's inverse
        self.W = (self.H_pl @ block_diagonal(self.landmark_inverse)).tocsr()
        S = sp.csr_matrix(H[:num_pose, :num_pose]) - self.W @ self.H_pl.T
        if damping > 0.0:
            S = S + damping * sp.identity(num_pose, format="csr")
        self.S = sp.csc_matrix(S)
        self.S.sort_indices()
        self.factor = factor(self.S) if num_pose else None

    def solve(self, b: np.ndarray, trans: str = "N") -> np.ndarray:
        """x (n,) of ``H x = b``: the poses' part from the reduced system, then each landmark's
        (``trans`` asks for the transpose's, the same: H is symmetric)."""
        b = np.asarray(b, dtype=float)
        columns = b.reshape(b.shape[0], -1)  # (n,) or (n, k) right-hand sides
        b_p, b_l = columns[: self.num_pose], columns[self.num_pose:]
        x_p = self.factor.solve(b_p - self.W @ b_l) if self.num_pose else np.zeros((0, columns.shape[1]))
        rhs = (b_l - self.H_pl.T @ x_p).reshape(-1, LANDMARK_DOF, columns.shape[1])
        x_l = np.einsum("lij,ljk->lik", self.landmark_inverse, rhs).reshape(-1, columns.shape[1])
        return np.concatenate([x_p, x_l]).reshape(b.shape)

    def landmark_covariances(self, *, by_solves: bool = False) -> np.ndarray:
        """The 3x3 diagonal blocks (L, 3, 3) of H^-1 belonging to the landmarks: their marginal
        covariances when H is an information matrix, ``Hll^-1 + W_l^T S^-1 W_l`` each.

        ``S^-1`` is needed only between poses that see a common landmark: pairs S couples, on the
        pattern of its factor, where selected inversion (``camloc.selected_inverse``) computes it
        at about the cost of the factorization. Should the factor's pattern not allow that, the
        same blocks come from solves with the factor, a block of right-hand sides at a time
        (exact too, but far slower on large problems); ``by_solves`` asks for that way.
        """
        cov = self.landmark_inverse.copy()
        if not self.num_pose:
            return cov
        from camloc.selected_inverse import PatternError, quadratic_forms, selected_inverse

        try:
            if by_solves:
                raise PatternError("asked for solves")
            coupled = self.W.copy()
            coupled.data[:] = 1.0  # positive: the pattern of W W^T, pairs of poses a landmark couples, without cancellation
            Z, perm = selected_inverse(*self.factor.ldl(), coupled @ coupled.T, closed=True)  # supernodal: closed
            cov += quadratic_forms(Z, perm, self.W, LANDMARK_DOF)
        except PatternError:
            cov += self._quadratic_forms_by_solves()
        return 0.5 * (cov + np.swapaxes(cov, 1, 2))

    def _quadratic_forms_by_solves(self) -> np.ndarray:
        W = self.W.tocsc()
        count = W.shape[1] // LANDMARK_DOF
        out = np.zeros((count, LANDMARK_DOF, LANDMARK_DOF))
        per_block = _COVARIANCE_BLOCK // LANDMARK_DOF
        for start in range(0, count, per_block):
            stop = min(start + per_block, count)
            W_block = W[:, LANDMARK_DOF * start: LANDMARK_DOF * stop].toarray()  # (num_pose, 3 k)
            X = self.factor.solve(W_block)  # S^-1 W_l for the k landmarks
            out[start:stop] = np.einsum("pla,plb->lab", W_block.reshape(self.num_pose, -1, LANDMARK_DOF),
                                        X.reshape(self.num_pose, -1, LANDMARK_DOF))
        return out
