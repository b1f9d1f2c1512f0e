"""Devices: ``--device`` parsing and resolution, images sent to the device as
uint8 and converted there, and the torch descriptors' device/uint8 paths.

No GPU exists where these tests were written: CUDA paths are checked for their refusals (a
clear ConfigError naming the setting) and every device-generic path runs on the CPU through
``torch.device``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet.backbones import autocast, bf16_native, check_device_spec, images_to_device, resolve_device
from fdnet.cli import main
from fdnet.data.images import list_images, load_image, load_image_uint8
from fdnet.descriptors import create
from fdnet.errors import ConfigError

from conftest import require_shared


def test_device_specs_are_checked_and_normalised():
    assert check_device_spec(None) == "auto"
    assert check_device_spec(" CUDA:01 ") == "cuda:1"
    for bad in ("gpu", "cuda:", "cuda:x", "mps", ""):
        with pytest.raises(ConfigError, match="choose auto, cpu, cuda or cuda:N"):
            check_device_spec(bad)


def test_auto_takes_the_cpu_without_a_gpu_and_cuda_is_refused_clearly():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    if torch.cuda.is_available():  # pragma: no cover - GPU machines
        assert resolve_device("auto").type == "cuda"
        with pytest.raises(ConfigError, match="GPU"):
            resolve_device(f"cuda:{torch.cuda.device_count()}")
        return
    assert resolve_device("auto") == torch.device("cpu")
    for spec in ("cuda", "cuda:0", "cuda:3"):
        with pytest.raises(ConfigError, match=r"--device cuda.*no CUDA GPU"):
            resolve_device(spec)


def test_bf16_native_and_autocast_follow_the_device():
    assert isinstance(bf16_native("cpu"), bool)
    x = torch.ones(2, 2)
    with autocast(torch.device("cpu"), True):
        assert (x @ x).dtype == torch.bfloat16
    with autocast(torch.device("cpu"), False):
        assert (x @ x).dtype == torch.float32


def test_uint8_images_convert_on_the_device_to_the_float_path_exactly(rng):
    u8 = rng.integers(0, 256, size=(3, 5, 7, 3), dtype=np.uint8)
    as_float = u8.astype(np.float32) / 255.0  # what load_image returns for 8-bit files
    for channels_last in (False, True):
        a = images_to_device(u8, torch.device("cpu"), channels_last=channels_last, mean=(0.5,) * 3, std=(0.5,) * 3)
        b = images_to_device(
            as_float, torch.device("cpu"), channels_last=channels_last, mean=(0.5,) * 3, std=(0.5,) * 3
        )
        assert a.dtype == torch.float32 and a.shape == (3, 3, 5, 7)
        assert torch.equal(a, b)
        assert a.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    with pytest.raises(ValueError, match="N, H, W, 3"):
        images_to_device(u8[..., :2], "cpu")


def test_uint8_loader_matches_the_float_loader(tmp_path, rng):
    rgb = rng.integers(0, 256, size=(30, 44, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "a.png")
    Image.fromarray(rgb).save(tmp_path / "a.jpg", quality=90)
    Image.fromarray(rgb[..., 0]).save(tmp_path / "g.png")
    rgba = np.concatenate([rgb, rng.integers(0, 256, size=(30, 44, 1), dtype=np.uint8)], axis=2)
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=16).save(tmp_path / "p.png")
    for name in ("a.png", "a.jpg", "g.png", "rgba.png", "p.png"):
        for size in (None, (15, 22), (60, 88)):
            u8 = load_image_uint8(tmp_path / name, size)
            assert u8.dtype == np.uint8 and u8.shape[-1] == 3
            np.testing.assert_array_equal(u8.astype(np.float32) / 255.0, load_image(tmp_path / name, size))
    deep = (rng.random((20, 30)) * 65535).astype(np.uint16)
    Image.fromarray(deep).save(tmp_path / "d16.png")
    u8 = load_image_uint8(tmp_path / "d16.png", (10, 15))
    np.testing.assert_allclose(u8 / 255.0, load_image(tmp_path / "d16.png", (10, 15)), atol=0.5 / 255 + 1e-6)


def test_create_passes_device_to_torch_methods_only():
    assert create("sad", device="cuda").name == "sad"  # numpy methods run on the CPU
    with pytest.raises(ConfigError, match="sad: device 'tpu'"):
        create("sad", device="tpu")
    d = create("conv3", dim=16, input_size=(32, 32), device="cpu", bf16=False)
    assert d.device == torch.device("cpu") and d.accepts_uint8
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            create("conv3", device="cuda")


@pytest.mark.parametrize(
    "name,options", [("conv3", {"dim": 32, "input_size": (32, 48)}), ("trunk", {"input_size": (32, 48)})]
)
@pytest.mark.parametrize("bf16", [False, True])
def test_torch_descriptors_take_uint8_images(rng, name, options, bf16):
    d = create(name, bf16=bf16, device="auto", **options)
    u8 = rng.integers(0, 256, size=(3, 32, 48, 3), dtype=np.uint8)
    np.testing.assert_array_equal(d.describe(u8), d.describe(u8.astype(np.float32) / 255.0))


def test_device_does_not_change_the_fingerprint():
    a = create("conv3", dim=16, input_size=(32, 32), bf16=False, device="cpu")
    b = create("conv3", dim=16, input_size=(32, 32), bf16=False)
    a.describe(np.zeros((1, 32, 32, 3), np.uint8))  # device copies made while describing ...
    assert a.fingerprint() == b.fingerprint()  # ... are not weights of their own


@pytest.fixture
def fdnet_run(tmp_path):
    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.model import FDNet
    from fdnet.runs import save_checkpoint

    config = preset("tiny")
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "run", FDNet(config.model).named_parts(), config, state={"step": 1})
    return tmp_path / "run"


@pytest.mark.parametrize("bf16", [False, True])
def test_fdnet_descriptor_uint8_and_both_vectors(fdnet_run, rng, bf16):
    d = create("fdnet", checkpoint=fdnet_run, bf16=bf16)
    assert d.device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    u8 = rng.integers(0, 256, size=(5, 16, 32, 3), dtype=np.uint8)
    content = d.describe(u8)
    np.testing.assert_array_equal(content, d.describe(u8.astype(np.float32) / 255.0))
    both = d.describe_both(u8)
    np.testing.assert_array_equal(both[0], content)
    np.testing.assert_array_equal(both[1], d.describe_appearance(u8))


def test_commands_refuse_a_missing_gpu_before_any_work(tmp_path, capsys):
    if torch.cuda.is_available():  # pragma: no cover
        pytest.skip("this machine has a GPU")
    images = tmp_path / "images"
    images.mkdir()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(images / "a.png")
    assert (
        main(
            [
                "match",
                "--reference",
                str(images),
                "--query",
                str(images),
                "--method",
                "conv3",
                "--device",
                "cuda:1",
                "--out",
                str(tmp_path / "m.csv"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("fdnet match: error: ") and "cuda:1" in err and "no CUDA GPU" in err
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                "x",
                "--images",
                str(images),
                "--out",
                str(tmp_path / "v.npz"),
                "--device",
                "gpu",
            ]
        )
        == 2
    )
    assert "--device 'gpu': choose auto, cpu, cuda or cuda:N" in capsys.readouterr().err


def test_training_flag_sets_runtime_device_of_every_trained_method():
    import argparse

    from fdnet.cli.common import add_training_arguments, apply_training_arguments
    from fdnet.methods.calc.config import PRESETS as CALC
    from fdnet.methods.fdnet.config import preset

    parser = argparse.ArgumentParser()
    add_training_arguments(parser)
    args = parser.parse_args(["--data", "d", "--out", "o", "--device", "CUDA:1"])
    assert apply_training_arguments(preset("tiny"), args).runtime.device == "cuda:1"
    unset = parser.parse_args(["--data", "d", "--out", "o"])
    assert apply_training_arguments(preset("tiny"), unset).runtime.device == "auto"
    cpu = parser.parse_args(["--data", "d", "--out", "o", "--device", "cpu"])
    assert apply_training_arguments(CALC["tiny"](), cpu).runtime.device == "cpu"
    # CALC (and NetVLAD) train where FDNet does: the same runtime.device
    assert apply_training_arguments(CALC["tiny"](), args).runtime.device == "cuda:1"
    bad = parser.parse_args(["--data", "d", "--out", "o", "--device", "gpu"])
    with pytest.raises(ConfigError, match="choose auto, cpu, cuda or cuda:N"):
        apply_training_arguments(CALC["tiny"](), bad)


def test_bf16_is_as_accurate_as_fp32_for_retrieval():
    """R@1 of the pretrained trunk (the map FDNet's cpu preset reads, and conv3's) with bf16
    autocast is within 0.5 points of fp32 on Gardens Point night -> day (200 queries,
    tolerance 2)."""
    root = require_shared("gardens_point")
    from fdnet.descriptors.base import describe_paths
    from fdnet.matching.similarity import top_k

    refs, queries = list_images(root / "day_right"), list_images(root / "night_right")
    recall = {}
    for bf16 in (False, True):
        d = create("trunk", bf16=bf16, device="cpu")
        r, q = describe_paths(d, refs, workers=0), describe_paths(d, queries, workers=0)
        best = top_k(q, r, 1)[0][:, 0]
        recall[bf16] = float((np.abs(best - np.arange(len(q))) <= 2).mean())
    assert abs(recall[True] - recall[False]) <= 0.005, recall
    assert recall[False] > 0.3  # a real retrieval, not noise


def test_compiled_content_pads_short_batches_and_matches_eager(fdnet_run, rng):
    eager = create("fdnet", checkpoint=fdnet_run, device="cpu", batch_size=4)
    compiled = create("fdnet", checkpoint=fdnet_run, device="cpu", batch_size=4, compile=True)
    u8 = rng.integers(0, 256, size=(6, 16, 32, 3), dtype=np.uint8)  # a full batch and a short one
    np.testing.assert_allclose(compiled.describe(u8), eager.describe(u8), atol=1e-5)
    assert compiled.fingerprint() == eager.fingerprint()


def test_content_vectors_are_the_same_in_passes_as_in_one(fdnet_run, rng):
    from fdnet.backbones import CachePasses

    d = create("fdnet", checkpoint=fdnet_run, device="cpu")
    u8 = rng.integers(0, 256, size=(5, 16, 32, 3), dtype=np.uint8)
    d._passes = CachePasses(cache_bytes=1 << 40)
    one = d.describe(u8)
    d._passes = CachePasses(cache_bytes=1)  # one image a pass
    np.testing.assert_allclose(d.describe(u8), one, atol=1e-5)


def test_a_failing_compile_falls_back_to_eager_once(fdnet_run, rng):
    d = create("fdnet", checkpoint=fdnet_run, device="cpu", batch_size=4, compile=True)

    def broken(x):
        raise RuntimeError("no C++ compiler here")

    d._content = broken
    u8 = rng.integers(0, 256, size=(3, 16, 32, 3), dtype=np.uint8)
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler here"):
        v = d.describe(u8)
    assert not d.compiled
    np.testing.assert_allclose(v, create("fdnet", checkpoint=fdnet_run, device="cpu").describe(u8), atol=1e-6)
