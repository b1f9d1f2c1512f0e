"""FAS: Mapping and Localization-2 with ground-truth pairs (here given as file names)."""

from fdnet.data.formats import detect_format, open_split

from .conftest import write_frames


def test_fas_pairs_by_file_name(tmp_path):
    root = tmp_path / "fas"
    write_frames(root / "Mapping", [f"m_{i:04d}.png" for i in range(10)])
    write_frames(root / "Localization-2", [f"l_{i:04d}.png" for i in range(6)])
    # localization frame i was taken where mapping frame i + 3 was
    (root / "groundtruth.txt").write_text("".join(f"l_{i:04d}.png m_{i + 3:04d}.png\n" for i in range(6)))
    assert detect_format(root) == "fas"
    split = open_split(root, split="all")
    assert (split.reference.name, split.query.name) == ("mapping", "localization-2")
    assert split.ground_truth.positives[0].tolist() == [0, 1, 2, 3, 4, 5, 6]  # m_3 +-3 frames
    assert split.ground_truth.positives[5].tolist() == [5, 6, 7, 8, 9]
    part = open_split(root, split="4:6", tolerance=0)
    assert part.reference.frame_ids.tolist() == [7, 8]
    assert [p.tolist() for p in part.ground_truth.positives] == [[0], [1]]


def test_fas_frames_named_by_timestamp_fall_back_to_positions(tmp_path):
    root = tmp_path / "fas"
    write_frames(root / "mapping", [f"{1000 + i}.5.png" for i in range(5)])  # "5" repeats: no frame numbers
    write_frames(root / "Localization_2", [f"{2000 + i}.5.png" for i in range(3)])
    (root / "gt.txt").write_text("0 2\n1 3\n2 4\n")  # positions, 0-based
    split = open_split(root, split="all", tolerance=0)
    assert [p.tolist() for p in split.ground_truth.positives] == [[2], [3], [4]]
