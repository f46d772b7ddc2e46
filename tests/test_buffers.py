"""The buffer-file schema: bit-exact round trip, validation errors, atomic writes."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from ppmrecon import buffers as B
from tests.conftest import make_buffer


def _raw_write(path, channels, header=None):
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    with OpenEXR.File(hdr, channels) as f:
        f.write(str(path))


def test_round_trip_bit_exact(tmp_path, buffer_file):
    path = tmp_path / "buf.exr"
    B.write_buffers(path, buffer_file)
    back = B.read_buffers(path)
    for name in ("estimates", "variances", "radii", "albedo", "normal", "depth"):
        a, b = getattr(buffer_file, name), getattr(back, name)
        assert a.shape == b.shape and b.dtype == np.float32
        assert np.array_equal(a, b), name
    for key, value in buffer_file.header.items():
        if isinstance(value, float):
            assert back.header[key] == pytest.approx(value, rel=1e-7)
        else:
            assert back.header[key] == value
    with OpenEXR.File(str(path), separate_channels=True) as f:
        assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION
        assert sorted(f.channels()) == sorted(B.channel_names())


def test_write_refuses_nan(tmp_path, buffer_file):
    buffer_file.estimates[2, 1, 1, 0] = np.nan
    with pytest.raises(B.NonFiniteError, match="z2.R"):
        B.write_buffers(tmp_path / "x.exr", buffer_file)
    assert not (tmp_path / "x.exr").exists()


def _channels(buf):
    return buf.channels()


@pytest.mark.parametrize("case, error, channel", [
    ("missing", B.MissingLayerError, "z3"),
    ("shape", B.ShapeMismatchError, None),
    ("uint", B.PixelTypeError, "depth.Z"),
    ("nan", B.NonFiniteError, "y.G"),
    ("inf", B.NonFiniteError, "normal.X"),
    ("negative", B.NegativeRadianceError, "z1.B"),
    ("newer", B.SchemaVersionError, B.H_VERSION),
])
def test_malformed_files(tmp_path, buffer_file, case, error, channel):
    ch = _channels(buffer_file)
    header = {k: v for k, v in buffer_file.header.items()}
    if case == "missing":
        for c in ("R", "G", "B", "V", "r"):
            del ch[f"z3.{c}"]
    elif case == "shape":  # a multi-part file whose parts disagree in size
        h, w = ch["depth.Z"].shape
        del ch["depth.Z"]
        window = (np.array([0, 0], np.int32), np.array([w - 1, h - 1], np.int32))
        base = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                "displayWindow": window}
        parts = [OpenEXR.Part(dict(base, **header), ch, "main"),
                 OpenEXR.Part(dict(base), {"depth.Z": np.zeros((3, 3), np.float32)}, "depth")]
        path = tmp_path / "shape.exr"
        with OpenEXR.File(parts) as f:
            f.write(str(path))
        with pytest.raises(error) as info:
            B.read_buffers(path)
        assert str(path) in str(info.value) and "depth.Z" in str(info.value)
        return
    elif case == "uint":
        ch["depth.Z"] = np.zeros(ch["depth.Z"].shape, np.uint32)
    elif case == "nan":
        ch["y.G"][0, 0] = np.nan
    elif case == "inf":
        ch["normal.X"][2, 3] = np.inf
    elif case == "negative":
        ch["z1.B"][1, 2] = -0.5
    elif case == "newer":
        header[B.H_VERSION] = B.SCHEMA_VERSION + 1
    path = tmp_path / f"{case}.exr"
    _raw_write(path, ch, header)
    with pytest.raises(error) as info:
        B.read_buffers(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg
    if channel:
        assert channel in msg


def test_not_exr_and_truncated(tmp_path, buffer_file):
    text = tmp_path / "notes.exr"
    text.write_text("hello, not an image\n")
    with pytest.raises(B.NotExrError, match="not an OpenEXR"):
        B.read_buffers(text)
    good = tmp_path / "good.exr"
    B.write_buffers(good, buffer_file)
    cut = tmp_path / "cut.exr"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(B.TruncatedFileError, match="truncated"):
        B.read_buffers(cut)


def test_float16_input_is_converted(tmp_path, buffer_file):
    ch = {k: v.astype(np.float16) for k, v in _channels(buffer_file).items()}
    path = tmp_path / "half.exr"
    _raw_write(path, ch, buffer_file.header)
    back = B.read_buffers(path)
    assert back.estimates.dtype == np.float32
    np.testing.assert_allclose(back.estimates, buffer_file.estimates, rtol=2e-3, atol=1e-3)


def test_rgb_only_file_names_missing_layers(tmp_path):
    path = tmp_path / "plain.exr"
    B.write_rgb(path, np.ones((4, 4, 3), np.float32))
    with pytest.raises(B.MissingLayerError, match="ppmrecon-render"):
        B.read_buffers(path)
    rgb, _ = B.read_rgb(path)
    assert rgb.shape == (4, 4, 3)


def test_interrupted_write_leaves_no_file(tmp_path, buffer_file, monkeypatch):
    path = tmp_path / "out.exr"
    real = OpenEXR.File

    class Exploding:
        def __init__(self, *a, **k):
            self._f = real(*a, **k)

        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

        def write(self, name):
            self._f.write(name)  # a complete temporary file exists ...
            raise RuntimeError("disk on fire")  # ... and then the process dies

    monkeypatch.setattr(OpenEXR, "File", Exploding)
    with pytest.raises(RuntimeError, match="disk on fire"):
        B.write_buffers(path, buffer_file)
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []  # the temporary file is cleaned up too


def test_overwrite_is_atomic(tmp_path):
    path = tmp_path / "ref.exr"
    B.write_rgb(path, np.zeros((2, 2, 3), np.float32))
    B.write_rgb(path, np.full((2, 2, 3), 2.0, np.float32))
    rgb, _ = B.read_rgb(path)
    assert (rgb == 2.0).all()
    assert [p.name for p in tmp_path.iterdir()] == ["ref.exr"]


def test_larger_buffer_round_trip(tmp_path):
    buf = make_buffer(33, 17, seed=5)
    B.write_buffers(tmp_path / "b.exr", buf)
    assert np.array_equal(B.read_buffers(tmp_path / "b.exr").normal, buf.normal)
