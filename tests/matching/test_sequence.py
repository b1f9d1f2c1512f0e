import numpy as np

from fdnet.matching.sequence import enhance_contrast, sequence_similarity


def test_sequence_matching_recovers_noisy_diagonal(rng):
    # A diagonal offset by 5 frames buried in noise: single images are often wrong,
    # sequences of 8 frames are nearly always right (away from the first frames).
    s = rng.normal(size=(80, 100)).astype(np.float32)
    s[np.arange(80), np.arange(80) + 5] += 2.0
    single = (s.argmax(1) == np.arange(80) + 5)[10:].mean()
    seq = (sequence_similarity(s, length=8).argmax(1) == np.arange(80) + 5)[10:].mean()
    assert seq > 0.9 and single < 0.5


def test_sequence_of_length_one_is_identity(rng):
    s = rng.normal(size=(5, 6)).astype(np.float32)
    np.testing.assert_array_equal(sequence_similarity(s, length=1), s)


def test_sequence_value_is_mean_along_line():
    s = np.arange(16, dtype=np.float32).reshape(4, 4)
    out = sequence_similarity(s, length=3, velocities=(1.0,))
    # ends at (3, 3): s[3,3], s[2,2], s[1,1]
    assert out[3, 3] == np.mean([s[3, 3], s[2, 2], s[1, 1]])
    # at q=0 only one frame is available
    assert out[0, 2] == s[0, 2]


def test_contrast_enhancement_normalises_rows(rng):
    s = rng.normal(size=(3, 200)).astype(np.float32) * 5 + 100
    e = enhance_contrast(s, window=21)
    assert abs(float(e[:, 20:-20].mean())) < 0.2
