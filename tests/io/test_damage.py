"""Truncated or corrupt files raise ImageError instead of decoding to filler."""

import cv2
import numpy as np
import pytest
from PIL import Image

from torchiid.core.exceptions import ImageError
from torchiid.io import load_image, load_mask


def _photo(h=96, w=128):
    """A textured picture, so that its compressed data are not trivially short."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 2, y * 2, (x + y)], axis=-1) % 256
    return np.clip(base + rng.normal(0, 12, (h, w, 3)), 0, 255).astype(np.uint8)


def _encode(ext, arr, params=()):
    ok, buf = cv2.imencode(ext, arr, list(params))
    assert ok
    return buf.tobytes()


def _expect_damaged(path, loader=load_image):
    with pytest.raises(ImageError, match="is truncated or corrupt") as info:
        loader(path)
    text = str(info.value)
    assert path.name in text and "\n" not in text
    return text


@pytest.fixture
def jpeg_bytes():
    return _encode(".jpg", _photo(), [cv2.IMWRITE_JPEG_QUALITY, 90])


@pytest.fixture
def png_bytes():
    return _encode(".png", _photo())


def _write(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    return path


def test_opencv_alone_returns_filler_for_a_truncated_jpeg(tmp_path, jpeg_bytes):
    # the reason for the check: OpenCV only warns and pads the missing part
    path = _write(tmp_path, "cut.jpg", jpeg_bytes[: len(jpeg_bytes) * 6 // 10])
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None
    _expect_damaged(path)


def test_valid_originals_load(tmp_path, jpeg_bytes, png_bytes):
    jpg = load_image(_write(tmp_path, "ok.jpg", jpeg_bytes))
    png = load_image(_write(tmp_path, "ok.png", png_bytes))
    assert jpg.image.shape == png.image.shape == (3, 96, 128)


def test_truncated_jpeg(tmp_path, jpeg_bytes):
    path = _write(tmp_path, "photo.jpg", jpeg_bytes[: len(jpeg_bytes) * 6 // 10])
    assert "JPEG image data" in _expect_damaged(path)


def test_jpeg_cut_just_before_eoi(tmp_path, jpeg_bytes):
    assert jpeg_bytes.endswith(b"\xff\xd9")
    _expect_damaged(_write(tmp_path, "noeoi.jpg", jpeg_bytes[:-2]))
    _expect_damaged(_write(tmp_path, "halfeoi.jpg", jpeg_bytes[:-1]))


def test_truncated_progressive_jpeg(tmp_path):
    data = _encode(".jpg", _photo(), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert load_image(_write(tmp_path, "prog.jpg", data)).image.shape == (3, 96, 128)
    _expect_damaged(_write(tmp_path, "prog60.jpg", data[: len(data) * 6 // 10]))
    _expect_damaged(_write(tmp_path, "prognoeoi.jpg", data[:-2]))


def test_jpeg_with_restart_markers(tmp_path):
    data = _encode(".jpg", _photo(), [cv2.IMWRITE_JPEG_RST_INTERVAL, 2])
    assert b"\xff\xd0" in data  # RST0 inside the scan must not end it
    assert load_image(_write(tmp_path, "rst.jpg", data)).image.shape == (3, 96, 128)
    _expect_damaged(_write(tmp_path, "rstcut.jpg", data[:-2]))


def test_bytes_after_the_jpeg_eoi_are_allowed(tmp_path, jpeg_bytes):
    # motion photos, MPF / gain-map images and padding follow the main image's EOI
    reference = load_image(_write(tmp_path, "ref.jpg", jpeg_bytes)).image
    small = _encode(".jpg", _photo(40, 40))
    for name, tail in [("pad.jpg", b"\x00" * 300), ("mpf.jpg", small), ("video.jpg", b"ftypmp42")]:
        loaded = load_image(_write(tmp_path, name, jpeg_bytes + tail)).image
        assert np.array_equal(loaded.numpy(), reference.numpy())


def test_an_eoi_inside_a_marker_segment_does_not_count(tmp_path, jpeg_bytes):
    # a comment segment holding FF D9 (as an EXIF thumbnail does) is skipped by its length
    payload = b"xx\xff\xd9yy"
    comment = b"\xff\xfe" + (len(payload) + 2).to_bytes(2, "big") + payload
    data = jpeg_bytes[:2] + comment + jpeg_bytes[2:]
    assert load_image(_write(tmp_path, "com.jpg", data)).image.shape == (3, 96, 128)
    _expect_damaged(_write(tmp_path, "comcut.jpg", data[: len(data) * 6 // 10]))


def test_jpeg_without_image_data(tmp_path, jpeg_bytes):
    _expect_damaged(_write(tmp_path, "empty.jpg", b"\xff\xd8\xff\xd9"))
    # a marker segment that claims more bytes than the file has
    _expect_damaged(_write(tmp_path, "seg.jpg", b"\xff\xd8\xff\xe0\x40\x00JFIF"))


def test_truncated_png(tmp_path, png_bytes):
    path = _write(tmp_path, "photo.png", png_bytes[: len(png_bytes) * 6 // 10])
    assert "PNG" in _expect_damaged(path)


def test_png_without_iend(tmp_path, png_bytes):
    assert png_bytes.endswith(b"IEND\xaeB`\x82")
    _expect_damaged(_write(tmp_path, "noiend.png", png_bytes[:-12]))


def _idat_data_offset(data):
    pos = 8
    while True:
        length = int.from_bytes(data[pos : pos + 4], "big")
        if data[pos + 4 : pos + 8] == b"IDAT":
            return pos + 8, length
        pos += 12 + length


def test_png_with_a_flipped_byte_in_idat(tmp_path, png_bytes):
    start, length = _idat_data_offset(png_bytes)
    data = bytearray(png_bytes)
    data[start + length // 2] ^= 0x10
    text = _expect_damaged(_write(tmp_path, "flip.png", bytes(data)))
    assert "CRC" in text and "IDAT" in text


def test_png_with_bad_ancillary_crc_or_trailing_bytes_loads(tmp_path):
    from PIL import PngImagePlugin

    arr = _photo()
    info = PngImagePlugin.PngInfo()
    info.add_text("comment", "hello")
    path = tmp_path / "text.png"
    Image.fromarray(arr).save(path, pnginfo=info)
    data = bytearray(path.read_bytes())
    data[data.find(b"tEXt") + 6] ^= 0xFF  # libpng ignores ancillary chunks with a bad CRC
    bad = _write(tmp_path, "badtext.png", bytes(data) + b"trailing bytes")
    loaded = load_image(bad, linear=True).image
    assert np.array_equal(np.round(loaded.permute(1, 2, 0).numpy() * 255).astype(np.uint8), arr)


def test_load_mask_rejects_damaged_files(tmp_path):
    mask = np.zeros((96, 128), np.uint8)
    mask[10:50, 10:50] = 255
    png = _encode(".png", mask)
    jpg = _encode(".jpg", mask)
    assert load_mask(_write(tmp_path, "m.png", png)).sum() == 1600
    _expect_damaged(_write(tmp_path, "mcut.png", png[: len(png) * 6 // 10]), load_mask)
    _expect_damaged(_write(tmp_path, "mcut.jpg", jpg[:-2]), load_mask)


@pytest.mark.parametrize("ext", [".tif", ".webp"])
def test_truncated_tiff_and_webp(tmp_path, ext):
    data = _encode(ext, _photo())
    assert load_image(_write(tmp_path, "ok" + ext, data)).image.shape == (3, 96, 128)
    with pytest.raises(ImageError) as info:
        load_image(_write(tmp_path, "cut" + ext, data[: len(data) * 6 // 10]))
    assert "cut" + ext in str(info.value) and "\n" not in str(info.value)


def test_tiff_strips_past_the_end_are_found_without_decoding(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    path = tmp_path / "raw.tif"
    tifffile.imwrite(path, _photo(), photometric="rgb", rowsperstrip=16)
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    assert "TIFF image data" in _expect_damaged(path)


def test_a_header_over_opencvs_pixel_cap_is_named(tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) & 0xFFFFFFFF
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0)  # 3.6e9 px declared
    path = tmp_path / "huge.png"
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )
    with pytest.raises(ImageError, match="declares more pixels than OpenCV decodes") as err:
        load_image(path)
    assert "OPENCV_IO_MAX_IMAGE_PIXELS" in str(err.value) and "loadsave.cpp" not in str(err.value)
