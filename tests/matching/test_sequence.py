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


def test_online_sequence_scores_equal_the_last_row_of_the_matrix_version(rng):
    from fdnet.matching.sequence import online_sequence_scores

    s = rng.normal(size=(12, 30)).astype(np.float32)
    offline = sequence_similarity(s, length=5)
    for q in range(12):
        rows = [s[i] for i in range(max(0, q - 4), q + 1)]
        np.testing.assert_allclose(online_sequence_scores(rows), offline[q], rtol=1e-6)


def test_online_sequence_scores_ignore_places_a_shorter_earlier_row_lacks():
    from fdnet.matching.sequence import online_sequence_scores

    # the earlier frame saw 2 places, the newest sees 4; velocity 1 only
    earlier = np.array([1.0, 3.0], dtype=np.float32)
    newest = np.array([0.0, 10.0, 20.0, 30.0], dtype=np.float32)
    out = online_sequence_scores([earlier, newest], velocities=(1.0,))
    # r=0: only the newest (earlier would be index -1); r=1: (10 + 1) / 2; r=2: (20 + 3) / 2;
    # r=3: earlier index 2 is past its 2 places, so the newest alone
    np.testing.assert_allclose(out, [0.0, 5.5, 11.5, 30.0])
    np.testing.assert_allclose(online_sequence_scores([earlier, newest], searchable=2, velocities=(1.0,)), [0.0, 5.5])
