"""DBoW: ORB features quantised by a vocabulary tree, TF-IDF weighted, compared by the L1 score.

Source: D. Gálvez-López and J. D. Tardós, "Bags of binary words for fast place recognition in
image sequences", IEEE T-RO 28(5), 2012 (DBoW2), with ORB features (Rublee et al., ICCV 2011) as
ORB-SLAM uses it (Mur-Artal et al., T-RO 2015):

- vocabulary: hierarchical k-means ("vocabulary tree", Nistér & Stewénius 2006) with branching
  ``k`` and depth ``L`` over binary descriptors. As in DBoW2's ``FORB``: k-means++ seeding with
  Hamming distance, cluster centres = per-bit majority of their members (the binary median),
  assignment by Hamming distance. Leaves are the words;
- weights: TF-IDF, ``tf = n_iw / n_i`` (word count over the image's feature count) and
  ``idf = log(N / N_w)`` over the N training images;
- score: ``s(v1, v2) = 1 - 0.5 * || v1/|v1| - v2/|v2| ||_1`` (L1-normalised vectors), in [0, 1].

Through the descriptor interface: ``describe`` returns the L1-normalised BoW vector densified
(dimension = number of words), and :meth:`DBoWDescriptor.similarity` computes the L1 score; for
non-negative L1-normalised vectors it equals ``sum_w min(v1_w, v2_w)`` (because
``|a - b| = a + b - 2 min(a, b)``), which is how it is computed, gathering only the query's
non-zero words. An image without keypoints (a black tunnel frame) gets the zero vector and scores
0 against everything.

Differences from DBoW2/ORB-SLAM:
- no direct index / geometric check / temporal consistency (the paper's baseline is the BoW
  similarity itself);
- a node with no more than ``k`` descriptors becomes a leaf (DBoW2 instead makes one child per
  descriptor); clustering runs at most ``max_iterations`` Lloyd steps per node;
- vocabularies are small (default k=10, L=4: at most 10^4 words, ORB-SLAM's has k=10, L=6) and,
  when none is supplied, learned from the reference images (``fit``), which the original would
  not do; a warning says so. ``fdnet vocabulary build`` learns one from other images.
- the vocabulary file is safetensors (arrays + YAML metadata), not DBoW2's text/binary format.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Sequence

import numpy as np
import yaml

from fdnet.data.images import load_images, to_grey
from fdnet.descriptors.base import Descriptor
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError, DataError, NotAvailableError
from fdnet.io import atomic_path

log = logging.getLogger(__name__)

DESCRIPTOR_BITS = 256  # ORB: 32 bytes


@dataclass
class ORBSettings:
    """OpenCV ORB settings (ORB-SLAM uses 8 levels at scale 1.2; it asks for 1000-2000 features
    on 640x480 frames, we default to 500 on smaller frames)."""

    nfeatures: int = 500
    scale_factor: float = 1.2
    nlevels: int = 8
    edge_threshold: int = 19
    patch_size: int = 19
    fast_threshold: int = 10

    def create(self):
        import cv2

        return cv2.ORB_create(
            nfeatures=int(self.nfeatures),
            scaleFactor=float(self.scale_factor),
            nlevels=int(self.nlevels),
            edgeThreshold=int(self.edge_threshold),
            patchSize=int(self.patch_size),
            fastThreshold=int(self.fast_threshold),
        )


def orb_features(images: np.ndarray, orb: ORBSettings) -> list[np.ndarray]:
    """(N, H, W, 3) float [0, 1] -> per image a (n_i, 32) uint8 array of ORB descriptors."""
    detector = orb.create()
    grey = np.clip(to_grey(np.asarray(images, dtype=np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    out = []
    for img in grey:
        _, desc = detector.detectAndCompute(img, None)
        out.append(desc if desc is not None else np.zeros((0, DESCRIPTOR_BITS // 8), np.uint8))
    return out


def _bits(packed: np.ndarray) -> np.ndarray:
    """(n, 32) uint8 -> (n, 256) float32 0/1, so Hamming distances are one BLAS product."""
    return np.unpackbits(packed, axis=1).astype(np.float32)


def _hamming(bits_a: np.ndarray, bits_b: np.ndarray) -> np.ndarray:
    """Hamming distances between rows of two 0/1 float matrices: |a| + |b| - 2 a.b (exact)."""
    return bits_a.sum(1)[:, None] + bits_b.sum(1)[None, :] - 2.0 * (bits_a @ bits_b.T)


def _kmeans_binary(bits: np.ndarray, k: int, rng: np.random.Generator, max_iterations: int):
    """k-means++ seeding + Lloyd iterations in Hamming space with majority-bit centres (DBoW2's
    FORB::meanValue). Returns (centres (k', 256) 0/1 float32, labels)."""
    n = len(bits)
    centres = [bits[rng.integers(n)]]
    d2 = _hamming(bits, centres[0][None])[:, 0] ** 2
    for _ in range(1, k):
        total = d2.sum()
        if total <= 0:  # all remaining descriptors coincide with a centre
            break
        pick = rng.choice(n, p=d2 / total)
        centres.append(bits[pick])
        d2 = np.minimum(d2, _hamming(bits, bits[pick][None])[:, 0] ** 2)
    centres = np.stack(centres)
    labels = np.full(n, -1)
    for _ in range(max_iterations):
        new_labels = np.argmin(_hamming(bits, centres), axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
        for c in range(len(centres)):
            members = bits[labels == c]
            if len(members):
                centres[c] = (members.mean(0) > 0.5).astype(np.float32)
    # drop empty clusters
    used = np.unique(labels)
    remap = np.full(len(centres), -1)
    remap[used] = np.arange(len(used))
    return centres[used], remap[labels]


@dataclass
class Vocabulary:
    """A vocabulary tree: node 0 is the root; ``children[node]`` holds up to ``branching`` child
    ids (-1 = none); ``centres[node]`` the node's packed 256-bit centre; ``word[node]`` the word id
    of a leaf (-1 for inner nodes); ``idf[word]`` its weight."""

    branching: int
    depth: int
    centres: np.ndarray  # (nodes, 32) uint8
    children: np.ndarray  # (nodes, branching) int32
    word: np.ndarray  # (nodes,) int32
    idf: np.ndarray  # (words,) float32
    info: dict = field(default_factory=dict)

    @property
    def num_words(self) -> int:
        return int(len(self.idf))

    # -- learning -------------------------------------------------------------------------
    @classmethod
    def learn(
        cls,
        features: Sequence[np.ndarray],
        branching: int = 10,
        depth: int = 4,
        seed: int = 0,
        max_iterations: int = 10,
        info: dict | None = None,
    ) -> "Vocabulary":
        """Hierarchical k-means over all images' ORB descriptors, then IDF over the images."""
        if branching < 2 or depth < 1:
            raise ConfigError(f"dbow: branching must be >= 2 and depth >= 1 (got k={branching}, L={depth})")
        features = [np.asarray(f, dtype=np.uint8).reshape(-1, DESCRIPTOR_BITS // 8) for f in features]
        packed = np.concatenate(features) if features else np.zeros((0, 32), np.uint8)
        if len(packed) <= branching:
            raise DataError(
                f"dbow: only {len(packed)} ORB features in {len(features)} training images; "
                "a vocabulary needs many more (are the images black, or too small?)"
            )
        bits = _bits(packed)
        rng = np.random.default_rng(seed)
        centres = [np.zeros(DESCRIPTOR_BITS, np.float32)]  # the root's centre is never used
        children: list[list[int]] = [[]]
        levels = [0]
        stack = [(0, np.arange(len(bits)))]
        while stack:
            node, members = stack.pop()
            if levels[node] == depth or len(members) <= branching:
                continue
            sub_centres, labels = _kmeans_binary(bits[members], branching, rng, max_iterations)
            if len(sub_centres) < 2:
                continue
            for c, centre in enumerate(sub_centres):
                child = len(centres)
                centres.append(centre)
                children.append([])
                levels.append(levels[node] + 1)
                children[node].append(child)
                stack.append((child, members[labels == c]))
        nodes = len(centres)
        child_table = np.full((nodes, branching), -1, np.int32)
        for node, kids in enumerate(children):
            child_table[node, : len(kids)] = kids
        is_leaf = np.array([not kids for kids in children])
        is_leaf[0] = False if children[0] else True
        word = np.full(nodes, -1, np.int32)
        word[is_leaf] = np.arange(int(is_leaf.sum()), dtype=np.int32)
        vocab = cls(
            branching=int(branching),
            depth=int(depth),
            centres=np.packbits(np.stack(centres).astype(np.uint8), axis=1),
            children=child_table,
            word=word,
            idf=np.zeros(int(is_leaf.sum()), np.float32),
            info=dict(info or {}),
        )
        # IDF over training images: idf_w = log(N / N_w) (DBoW2 TF_IDF); unseen words get log(N).
        n_images = len(features)
        containing = np.zeros(vocab.num_words, np.float64)
        for f in features:
            if len(f):
                containing[np.unique(vocab.words(f))] += 1
        vocab.idf = np.log(n_images / np.maximum(containing, 1.0)).astype(np.float32)
        vocab.info.update(
            {
                "training_images": n_images,
                "training_features": int(len(packed)),
                "seed": int(seed),
                "max_iterations": int(max_iterations),
            }
        )
        return vocab

    # -- use ------------------------------------------------------------------------------
    def words(self, packed: np.ndarray) -> np.ndarray:
        """Word id of each (n, 32) uint8 descriptor: descend the tree by nearest child (Hamming)."""
        if len(packed) == 0:
            return np.zeros(0, np.int64)
        bits = _bits(np.asarray(packed, dtype=np.uint8))
        centre_bits = _bits(self.centres)
        node = np.zeros(len(bits), np.int64)
        for _ in range(self.depth + 1):
            kids = self.children[node]  # (n, k)
            active = kids[:, 0] >= 0
            if not active.any():
                break
            idx = np.where(active)[0]
            k = kids[idx]
            cand = centre_bits[np.maximum(k, 0)]  # (m, k, 256)
            dist = (bits[idx, None, :] != cand).sum(-1).astype(np.float32)
            dist[k < 0] = np.inf
            node[idx] = k[np.arange(len(idx)), np.argmin(dist, axis=1)]
        return self.word[node].astype(np.int64)

    def bow(self, packed: np.ndarray) -> np.ndarray:
        """TF-IDF bag of words of one image, L1-normalised; zeros when it has no features."""
        v = np.zeros(self.num_words, np.float32)
        if len(packed) == 0:
            return v
        counts = np.bincount(self.words(packed), minlength=self.num_words).astype(np.float32)
        v = counts / len(packed) * self.idf
        total = v.sum()
        return v / total if total > 0 else np.zeros_like(v)

    # -- files ----------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        from safetensors.numpy import save_file

        meta = {
            "format": "fdnet-dbow-vocabulary-1",
            "branching": self.branching,
            "depth": self.depth,
            "num_words": self.num_words,
            **self.info,
        }
        tensors = {
            "centres": np.ascontiguousarray(self.centres),
            "children": self.children,
            "word": self.word,
            "idf": self.idf,
        }
        with atomic_path(path) as tmp:
            try:
                save_file(tensors, str(tmp), metadata={"config": yaml.safe_dump(meta, sort_keys=False)})
            except Exception as exc:
                # safetensors reports a failed write (a full disk) as its own error type, with the
                # OS error number only in the text: an OSError here is one clear line from atomic_path
                found = re.search(r"os error (\d+)", str(exc))
                if found is None:
                    raise
                raise OSError(int(found.group(1)), os.strerror(int(found.group(1))), str(tmp)) from exc

    @classmethod
    def load(cls, path: str | Path) -> "Vocabulary":
        from safetensors import safe_open

        path = Path(path)
        if not path.is_file():
            raise NotAvailableError(
                f"{path}: DBoW vocabulary file not found "
                "(build one with `fdnet vocabulary build --images DIR --out FILE`)"
            )
        try:
            with safe_open(str(path), framework="numpy") as f:
                meta = yaml.safe_load((f.metadata() or {}).get("config", "")) or {}
                arrays = {k: f.get_tensor(k) for k in f.keys()}
        except Exception as exc:  # any reader failure means the file is not a vocabulary
            raise ConfigError(f"{path}: not a DBoW vocabulary file ({exc.__class__.__name__}: {exc})") from exc
        if meta.get("format") != "fdnet-dbow-vocabulary-1" or not {"centres", "children", "word", "idf"} <= set(arrays):
            raise ConfigError(f"{path}: not an fdnet DBoW vocabulary (missing format tag or arrays)")
        info = {k: v for k, v in meta.items() if k not in ("format", "branching", "depth", "num_words")}
        return cls(
            branching=int(meta["branching"]),
            depth=int(meta["depth"]),
            centres=arrays["centres"].astype(np.uint8),
            children=arrays["children"].astype(np.int32),
            word=arrays["word"].astype(np.int32),
            idf=arrays["idf"].astype(np.float32),
            info=info,
        )


def learn_vocabulary(
    paths: Sequence[str | Path],
    input_size=(288, 512),
    orb: ORBSettings | None = None,
    branching: int = 10,
    depth: int = 4,
    seed: int = 0,
    batch: int = 32,
    progress: bool = False,
) -> Vocabulary:
    """Load ``paths`` at ``input_size``, extract ORB features and learn a vocabulary."""
    orb = orb or ORBSettings()
    features: list[np.ndarray] = []
    chunks = range(0, len(paths), batch)
    if progress:
        from fdnet.progress import progress_bar

        chunks = progress_bar(chunks, desc="ORB features", unit="batch", leave=False)
    for start in chunks:
        features.extend(orb_features(load_images(paths[start : start + batch], input_size), orb))
    info = {"input_size": [int(s) for s in input_size], "orb": {k: v for k, v in orb.__dict__.items()}}
    return Vocabulary.learn(features, branching=branching, depth=depth, seed=seed, info=info)


@dataclass(frozen=True)
class DBoWSettings(MethodSettings):
    method: ClassVar[str] = "dbow"
    #: vocabulary file from ``fdnet vocabulary build`` (--vocabulary); without one, one is learnt
    vocabulary: str | None = None
    #: children per node of a learnt vocabulary tree
    branching: int = 10
    #: levels of a learnt vocabulary tree
    depth: int = 4
    #: (height, width) images are resized to, [H, W] or HxW
    input_size: tuple[int, int] | str = (288, 512)
    #: ORB features per image
    nfeatures: int = 500
    #: ORB pyramid scale between levels
    scale_factor: float = 1.2
    #: ORB pyramid levels
    nlevels: int = 8
    #: ORB border where no features are detected, in pixels
    edge_threshold: int = 19
    #: ORB patch side, in pixels
    patch_size: int = 19
    #: FAST corner threshold
    fast_threshold: int = 10
    #: seed of the vocabulary's k-means
    seed: int = 0
    #: dataset folder to learn the vocabulary from (--fit; default the reference images)
    fit: str | None = None
    #: START:END frames of each of fit's conditions (--fit-frames)
    fit_frames: str | None = None

    def check(self) -> None:
        from fdnet.descriptors.fitting import check_fit_frames

        vocabulary, fit = self.need_path("vocabulary"), self.need_path("fit")
        self.need_whole("branching", minimum=2, maximum=1000)
        self.need_whole("depth", minimum=1, maximum=10)
        self.need_size("input_size")
        self.need_whole("nfeatures", minimum=1)
        self.need_number("scale_factor", above=1.0)
        self.need_whole("nlevels", minimum=1, maximum=32)
        self.need_whole("edge_threshold", minimum=0)
        self.need_whole("patch_size", minimum=2)
        self.need_whole("fast_threshold", minimum=0, maximum=255)
        self.need_whole("seed", minimum=0)
        fit_frames = check_fit_frames(self.fit_frames, "dbow")
        if (fit or fit_frames) and vocabulary:
            raise ConfigError("dbow: give either a vocabulary file or a folder to learn one from (--fit), not both")
        if fit_frames and not fit:
            raise ConfigError(f"dbow: fit_frames ({fit_frames}) needs fit=DIR (--fit DIR) to take the frames of")


class DBoWDescriptor(Descriptor):
    """DBoW2-style ORB bag of words (Gálvez-López & Tardós 2012); see the module docstring.

    Settings (:class:`DBoWSettings`): ``vocabulary`` (file from ``fdnet vocabulary build``; when
    absent ``fit`` learns one from the reference images), ``branching``/``depth`` (for a learned
    vocabulary), ``nfeatures`` and the other ORB settings, ``input_size``, ``seed``, ``fit`` (a
    dataset folder to learn the vocabulary from instead of the reference images: every condition
    sub-folder, ``fit_frames=START:END`` of each; :mod:`fdnet.descriptors.fitting`).
    ``settings()["fitted_on"]`` says what the vocabulary was learnt from.
    """

    name = "dbow"
    dot_product_similarity = False
    Settings: ClassVar[type] = DBoWSettings

    def __init__(self, settings: DBoWSettings | None = None, **options):
        from fdnet.descriptors.fitting import check_fit_frames, fit_image_paths

        conf = self.conf = DBoWSettings.build(settings, options)
        vocabulary = conf.vocabulary
        self.input_size = conf.need_size("input_size")
        self.orb = ORBSettings(
            int(conf.nfeatures),
            float(conf.scale_factor),
            int(conf.nlevels),
            int(conf.edge_threshold),
            int(conf.patch_size),
            int(conf.fast_threshold),
        )
        self.branching = int(conf.branching)
        self.depth = int(conf.depth)
        self.seed = int(conf.seed)
        self.fit_folder = str(conf.fit) if conf.fit else None
        self.fit_frames = check_fit_frames(conf.fit_frames, "dbow")
        self.vocabulary_path = str(vocabulary) if vocabulary else None
        self.vocabulary: Vocabulary | None = Vocabulary.load(vocabulary) if vocabulary else None
        if self.vocabulary is not None:
            self.branching, self.depth = self.vocabulary.branching, self.vocabulary.depth
        self.fitted_on = "vocabulary file" if self.vocabulary is not None else None
        if self.fit_folder:
            paths, self.fitted_on = fit_image_paths(self.fit_folder, self.fit_frames, where="dbow: --fit")
            self.vocabulary = learn_vocabulary(paths, self.input_size, self.orb, self.branching, self.depth, self.seed)

    @property
    def needs_fit(self) -> bool:
        return self.vocabulary is None

    @property
    def dim(self) -> int:
        if self.vocabulary is None:
            raise ConfigError("dbow: no vocabulary yet; pass vocabulary=FILE or call fit() first")
        return self.vocabulary.num_words

    def settings(self) -> dict:
        learnt = (
            "learned from " + (self.fitted_on if self.fit_folder else "the reference images")
            if self.vocabulary is not None
            else None
        )
        out = {
            "input_size": list(self.input_size),
            "orb": dict(self.orb.__dict__),
            "branching": self.branching,
            "depth": self.depth,
            "vocabulary": self.vocabulary_path or learnt,
            "fitted_on": self.fitted_on,
        }
        if self.fit_folder:
            out.update({"fit": self.fit_folder, "fit_frames": self.fit_frames})
        if self.vocabulary is not None:
            out["num_words"] = self.vocabulary.num_words
            out["vocabulary_training_images"] = self.vocabulary.info.get("training_images")
        return out

    def fit(self, images_or_paths) -> None:
        """Learn a vocabulary (k=branching, L=depth) from these images when none was given."""
        if self.vocabulary is not None:
            return
        if isinstance(images_or_paths, np.ndarray):
            features = orb_features(images_or_paths, self.orb)
            info = {"input_size": list(self.input_size), "orb": dict(self.orb.__dict__)}
            self.vocabulary = Vocabulary.learn(features, self.branching, self.depth, self.seed, info=info)
        else:
            self.vocabulary = learn_vocabulary(
                list(images_or_paths), self.input_size, self.orb, self.branching, self.depth, self.seed
            )
        from fdnet.descriptors.fitting import REFERENCE_IMAGES

        self.fitted_on = f"{REFERENCE_IMAGES} ({self.vocabulary.info.get('training_images', 0)})"
        log.warning(
            "dbow: no vocabulary given; learned one (k=%d, L=%d, %d words) from %d reference "
            "images. Use `fdnet vocabulary build` to learn one from separate training images.",
            self.branching,
            self.depth,
            self.vocabulary.num_words,
            self.vocabulary.info.get("training_images", 0),
        )

    def describe(self, images: np.ndarray) -> np.ndarray:
        if self.vocabulary is None:
            raise ConfigError(
                "dbow: no vocabulary; pass vocabulary=FILE (fdnet vocabulary build) "
                "or fit() on reference images first"
            )
        features = orb_features(images, self.orb)
        return np.stack([self.vocabulary.bow(f) for f in features]) if features else np.zeros((0, self.dim), np.float32)

    def similarity(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        """DBoW2 L1 score 1 - 0.5 |q - r|_1 = sum_w min(q_w, r_w) for L1-normalised vectors;
        0 when either has no words. Only the query's non-zero words are gathered."""
        q = np.asarray(queries, dtype=np.float32)
        r = np.asarray(references, dtype=np.float32)
        out = np.zeros((len(q), len(r)), dtype=np.float32)
        for i, row in enumerate(q):
            nz = np.flatnonzero(row)
            if len(nz):
                out[i] = np.minimum(r[:, nz], row[nz]).sum(axis=1)
        return out
