"""Reading images of any common format into float32 RGB in [0, 1]."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from fdnet.data.images import image_size, list_images, load_image, load_images, natural_key, to_grey
from fdnet.errors import DataError

from conftest import require_shared


def _save(path, array, mode=None, **kw):
    im = Image.fromarray(array) if mode is None else Image.fromarray(array).convert(mode)
    im.save(path, **kw)
    return path


@pytest.fixture
def rgb8(rng):
    return (rng.random((24, 40, 3)) * 255).astype(np.uint8)


def test_png_rgb_exact(tmp_path, rgb8):
    out = load_image(_save(tmp_path / "a.png", rgb8))
    assert out.dtype == np.float32 and out.shape == (24, 40, 3)
    np.testing.assert_allclose(out, rgb8 / 255.0, atol=1e-6)


def test_jpeg_rgb_close(tmp_path):
    smooth = np.zeros((32, 48, 3), np.uint8)
    smooth[..., 0] = np.linspace(0, 255, 48)[None].astype(np.uint8)
    smooth[..., 2] = 128
    out = load_image(_save(tmp_path / "a.jpg", smooth, quality=95))
    assert out.shape == (32, 48, 3)
    assert np.abs(out - smooth / 255.0).mean() < 0.02


def test_grey_becomes_three_equal_channels(tmp_path, rgb8):
    grey = rgb8[..., 0]
    out = load_image(_save(tmp_path / "g.png", grey))
    assert out.shape == (24, 40, 3)
    np.testing.assert_allclose(out[..., 0], grey / 255.0, atol=1e-6)
    assert np.array_equal(out[..., 0], out[..., 2])


def test_rgba_is_composited_on_black(tmp_path):
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[:2, :, 3] = 255  # top half opaque
    rgba[2:, :, 3] = 0  # bottom half transparent
    out = load_image(_save(tmp_path / "a.png", rgba))
    np.testing.assert_allclose(out[:2], 200 / 255.0, atol=1e-6)
    np.testing.assert_allclose(out[2:], 0.0, atol=1e-6)


def test_palette_and_la_images(tmp_path, rgb8):
    p = Image.fromarray(rgb8).convert("P", palette=Image.Palette.ADAPTIVE, colors=16)
    p.save(tmp_path / "p.png")
    out = load_image(tmp_path / "p.png")
    np.testing.assert_allclose(out, np.asarray(p.convert("RGB")) / 255.0, atol=1e-6)
    assert load_image(tmp_path / "p.png", size=(12, 20)).shape == (12, 20, 3)
    la = Image.fromarray(np.stack([rgb8[..., 0], np.full((24, 40), 255, np.uint8)], axis=2), mode="LA")
    la.save(tmp_path / "la.png")
    np.testing.assert_allclose(load_image(tmp_path / "la.png")[..., 1], rgb8[..., 0] / 255.0, atol=1e-6)


@pytest.mark.parametrize("size", [None, (8, 16)])
def test_16bit_png_scaled_by_65535_even_when_dark(tmp_path, size):
    bright = (np.linspace(0, 65535, 16 * 32).reshape(16, 32)).astype(np.uint16)
    dark = np.full((16, 32), 200, np.uint16)  # no value above 255: still 16-bit, so very dark
    b = load_image(_save(tmp_path / "b.png", bright), size)
    d = load_image(_save(tmp_path / "d.png", dark), size)
    assert b.dtype == np.float32 and 0.0 <= b.min() and b.max() <= 1.0
    assert b.max() > 0.9
    np.testing.assert_allclose(d, 200 / 65535, atol=1e-5)


def test_resize_to_requested_height_width(tmp_path, rgb8):
    path = _save(tmp_path / "a.png", rgb8)
    assert load_image(path, (12, 20)).shape == (12, 20, 3)  # shrink
    assert load_image(path, (48, 80)).shape == (48, 80, 3)  # enlarge
    flat = np.full((24, 40, 3), 77, np.uint8)
    np.testing.assert_allclose(load_image(_save(tmp_path / "f.png", flat), (6, 10)), 77 / 255.0, atol=1e-6)
    with pytest.raises(DataError, match="not positive"):
        load_image(path, (0, 10))


def test_corrupt_truncated_and_missing_files_name_the_file(tmp_path, rgb8):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"this is not an image at all")
    with pytest.raises(DataError, match="junk.png: cannot read image"):
        load_image(junk)
    good = _save(tmp_path / "good.png", rgb8)
    cut = tmp_path / "cut.png"
    cut.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    with pytest.raises(DataError, match="cut.png"):
        load_image(cut, (8, 8))
    with pytest.raises(DataError, match="nope.jpg: image file not found"):
        load_image(tmp_path / "nope.jpg")
    # In a batch the error still names the bad file.
    paths = [good] * 9 + [junk]
    with pytest.raises(DataError, match="junk.png"):
        load_images(paths, (8, 8))


def test_load_images_batch_matches_single_loads(tmp_path, rng):
    paths = [_save(tmp_path / f"{i:02d}.png", (rng.random((10, 14, 3)) * 255).astype(np.uint8)) for i in range(10)]
    batch = load_images(paths, (5, 7))
    assert batch.shape == (10, 5, 7, 3) and batch.dtype == np.float32
    for i, p in enumerate(paths):
        np.testing.assert_array_equal(batch[i], load_image(p, (5, 7)))
    assert load_images([], (5, 7)).shape == (0, 5, 7, 3)


def test_list_images_sorted_filtered_and_errors(tmp_path, rgb8):
    for name in ["b.png", "a.JPG", "c.txt", ".hidden.csv"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.png").mkdir()
    assert [p.name for p in list_images(tmp_path)] == ["a.JPG", "b.png"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="empty: contains no images"):
        list_images(empty)
    with pytest.raises(DataError, match="not a folder"):
        list_images(tmp_path / "missing")


def test_list_images_natural_order_of_unpadded_frame_numbers(tmp_path):
    names = [f"frame_{i}.png" for i in range(1, 13)]
    for name in reversed(names):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == names  # frame_2 before frame_10


def test_natural_key_is_total_case_sensitive_and_numeric():
    names = ["b2.png", "B10.png", "a10.png", "a2.png", "a02.png", "B9.png"]
    # digits as numbers; text case-sensitively ("B" < "a" < "b", as plain sorting); leading zeros
    # tie on the number and the plain name breaks the tie ("a02" < "a2")
    assert sorted(names, key=natural_key) == ["B9.png", "B10.png", "a02.png", "a2.png", "a10.png", "b2.png"]
    assert natural_key("frame_01.png") != natural_key("frame_1.png")
    assert sorted(["x²1", "x10", "x9"], key=natural_key) == ["x9", "x10", "x²1"]  # no int("²")


def test_list_images_recursive_and_hidden_files(tmp_path):
    for rel in ["b/1.png", "a/10.png", "a/2.png", "a/._2.png", ".cache/0.png", "3.png"]:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x")
    assert [p.relative_to(tmp_path).as_posix() for p in list_images(tmp_path, recursive=True)] == [
        "3.png",
        "a/2.png",
        "a/10.png",
        "b/1.png",
    ]
    assert [p.name for p in list_images(tmp_path)] == ["3.png"]


@pytest.mark.parametrize("warnings_as_errors", [False, True])
@pytest.mark.parametrize("side, pillow_reaction", [(12, "warns"), (20, "raises")])
def test_images_over_the_pixel_limit_are_data_errors_naming_the_file(
    tmp_path, monkeypatch, side, pillow_reaction, warnings_as_errors
):
    """Pillow warns above MAX_IMAGE_PIXELS and raises above twice that; fdnet refuses both, with the
    file and its pixel count, whether or not warnings are errors (python -W error)."""
    import warnings

    path = _save(tmp_path / "huge.png", np.zeros((side, side, 3), np.uint8))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # a 12x12 image is then "too big" (144 > 100)
    with warnings.catch_warnings():
        warnings.simplefilter("error" if warnings_as_errors else "ignore", Image.DecompressionBombWarning)
        for read in (load_image, image_size, lambda p: load_images([p], (4, 4))):
            with pytest.raises(DataError, match=rf"huge.png: image has {side * side} pixels.*limit of 100 pixels"):
                read(path)
    assert load_image(_save(tmp_path / "small.png", np.zeros((10, 10, 3), np.uint8))).shape == (10, 10, 3)


def test_to_grey_bt601(rng):
    x = rng.random((2, 3, 4, 3)).astype(np.float32)
    expected = 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]
    np.testing.assert_allclose(to_grey(x), expected, rtol=1e-6)
    assert to_grey(np.ones((1, 2, 2, 3), np.float32)).max() == pytest.approx(1.0)


def test_real_images_of_each_shared_dataset():
    gp = require_shared("gardens_point")
    day = load_image(gp / "day_right" / "Image000.jpg")
    night = load_image(gp / "night_right" / "Image000.jpg")
    assert day.shape == (540, 960, 3) and night.shape == (360, 640, 3)
    assert load_image(gp / "night_right" / "Image000.jpg", (60, 80)).shape == (60, 80, 3)
    nordland = require_shared("nordland_trimmed")
    im = load_image(nordland / "summer" / "images-00500.png")
    assert im.shape == (32, 64, 3) and np.array_equal(im[..., 0], im[..., 1])  # grey stored as RGB


def test_a_symbolic_link_to_nothing_among_the_images_is_refused(tmp_path, rgb8):
    from fdnet.data.images import list_images
    from fdnet.errors import DataError

    for i in range(3):
        Image.fromarray(rgb8).save(tmp_path / f"{i}.png")
    (tmp_path / "1.png").unlink()
    (tmp_path / "1.png").symlink_to(tmp_path / "moved-away.png")
    (tmp_path / ".hidden.png").symlink_to(tmp_path / "gone.png")  # hidden files are not images: ignored
    with pytest.raises(DataError, match=r"1.png: a symbolic link to .*moved-away.png, which does not exist"):
        list_images(tmp_path)
    (tmp_path / "1.png").unlink()
    (tmp_path / "1.png").symlink_to(tmp_path / "0.png")  # a link to an image is an image
    assert [p.name for p in list_images(tmp_path)] == ["0.png", "1.png", "2.png"]
