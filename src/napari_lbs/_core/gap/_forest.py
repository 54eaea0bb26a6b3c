"""A random forest kept as plain arrays: trained with scikit-learn, saved and evaluated without pickle.

The forest answers several yes/no questions at once (one output per catalog effect: is it
present?). Its trees are flattened into arrays (children, split feature, threshold, each
output's share of "yes" in the leaf), so a cached forest is read with
``numpy.load(allow_pickle=False)`` and evaluated in numpy: nothing a file holds is executed.
(Breiman 2001; ABC model choice with random forests: Pudlo et al. 2016.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ForestArrays", "train_forest"]


@dataclass(frozen=True)
class ForestArrays:
    """A trained forest: node arrays of all trees concatenated; ``roots[t]`` is tree t's first node.

    ``left``/``right`` are absolute node indices (−1 at a leaf); ``value`` is (nodes, outputs):
    each output's probability of "yes" among the training examples in that node.
    """

    roots: np.ndarray
    left: np.ndarray
    right: np.ndarray
    feature: np.ndarray
    threshold: np.ndarray
    value: np.ndarray

    def leaves(self, x: np.ndarray) -> np.ndarray:
        """(examples, trees) int: the leaf each example ends in, per tree."""
        x = np.asarray(x, np.float32)
        node = np.broadcast_to(self.roots, (x.shape[0], self.roots.size)).copy()
        rows = np.arange(x.shape[0])[:, None]
        while True:
            inner = self.left[node] >= 0
            if not inner.any():
                return node
            go_left = x[rows, np.maximum(self.feature[node], 0)] <= self.threshold[node]
            node = np.where(inner, np.where(go_left, self.left[node], self.right[node]), node)

    def predict(self, x: np.ndarray) -> np.ndarray:
        """(examples, outputs): the forest's probability of "yes" for each output (the trees' mean)."""
        return self.value[self.leaves(x)].mean(axis=1)

    def arrays(self, prefix: str = "forest_") -> dict:
        """The forest as named arrays for `numpy.savez`."""
        return {f"{prefix}{name}": getattr(self, name) for name in ("roots", "left", "right", "feature", "threshold", "value")}

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "forest_") -> ForestArrays:
        """The forest from `arrays`' output (raises ValueError on arrays of the wrong type, shape or range).

        Everything a forest's evaluation relies on is checked, so a damaged or crafted file
        can neither index out of its arrays, loop, nor answer a probability outside [0, 1].
        """
        forest = cls(**{name: np.asarray(arrays[f"{prefix}{name}"]) for name in ("roots", "left", "right", "feature", "threshold", "value")})
        for name in ("roots", "left", "right", "feature"):
            if getattr(forest, name).dtype.kind not in "iu" or getattr(forest, name).ndim != 1:
                raise ValueError(f"forest {name}: expected a 1-D integer array, got {getattr(forest, name).dtype} of shape {getattr(forest, name).shape}")
        if forest.threshold.dtype.kind != "f" or forest.threshold.ndim != 1 or forest.value.dtype.kind != "f" or forest.value.ndim != 2:
            raise ValueError("forest threshold and value: expected 1-D and 2-D float arrays")
        nodes = forest.left.size
        if not (forest.right.size == forest.feature.size == forest.threshold.size == forest.value.shape[0] == nodes) or not forest.roots.size:
            raise ValueError("forest arrays of different lengths, or no tree")
        for name in ("left", "right"):
            values = getattr(forest, name)
            if values.size and (values.min() < -1 or values.max() >= nodes):
                raise ValueError(f"forest {name} out of range")
        if forest.roots.min() < 0 or forest.roots.max() >= nodes:
            raise ValueError("forest roots out of range")
        inner = forest.left >= 0
        if np.any(inner != (forest.right >= 0)) or np.any(forest.feature[inner] < 0):
            raise ValueError("forest nodes with one child, or a split on no feature")
        if np.any(forest.left[inner] <= np.flatnonzero(inner)) or np.any(forest.right[inner] <= np.flatnonzero(inner)):
            raise ValueError("forest children must come after their node (a cycle would never end)")
        if np.any(np.isnan(forest.threshold[inner])):
            raise ValueError("forest thresholds: NaN at a split")
        if not np.all((forest.value >= 0.0) & (forest.value <= 1.0)):  # NaN fails too
            raise ValueError("forest values: expected shares in [0, 1]")
        return forest


def train_forest(x: np.ndarray, y: np.ndarray, *, trees: int = 300, min_leaf: int = 2, seed: int = 0, jobs: int = 1) -> ForestArrays:
    """Fit a random forest of ``trees`` to ``x`` (examples, features) and the yes/no answers ``y`` (examples, outputs).

    Every tree sees a bootstrap sample and a random √features at each split (scikit-learn's
    `RandomForestClassifier`); ``seed`` makes it reproducible.
    """
    from sklearn.ensemble import RandomForestClassifier

    y = np.asarray(y, bool)
    model = RandomForestClassifier(n_estimators=trees, min_samples_leaf=min_leaf, max_features="sqrt", random_state=seed, n_jobs=jobs)
    model.fit(np.asarray(x, np.float32), y.astype(np.int8))
    roots, left, right, feature, threshold, value = [], [], [], [], [], []
    offset = 0
    for estimator in model.estimators_:
        tree = estimator.tree_
        n = tree.node_count
        counts = tree.value  # (nodes, outputs, classes), as counts or shares
        share = counts / np.maximum(counts.sum(axis=2, keepdims=True), 1e-12)
        yes = np.zeros((n, y.shape[1]), np.float32)
        for k, classes in enumerate(estimator.classes_ if isinstance(estimator.classes_, list) else [estimator.classes_]):
            classes = np.asarray(classes)
            if (classes == 1).any():
                yes[:, k] = share[:, k, int(np.flatnonzero(classes == 1)[0])]
        roots.append(offset)
        is_leaf = tree.children_left < 0
        left.append(np.where(is_leaf, -1, tree.children_left + offset))
        right.append(np.where(is_leaf, -1, tree.children_right + offset))
        feature.append(np.where(is_leaf, -1, tree.feature))
        threshold.append(tree.threshold.astype(np.float64))  # sklearn's own: float32 inputs against float64 midpoints
        value.append(yes)
        offset += n
    return ForestArrays(
        np.asarray(roots, np.int64), np.concatenate(left).astype(np.int64), np.concatenate(right).astype(np.int64),
        np.concatenate(feature).astype(np.int64), np.concatenate(threshold), np.concatenate(value),
    )
