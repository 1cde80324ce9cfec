"""Scene text files (issue 26): list files and transforms.json decoded when their encoding is announced (byte-order
mark) or UTF-8, refused with the file and the reason otherwise; names with invisible characters shown escaped."""

import pytest

from kc_splatfacto.data.base import DataParserError, read_split_list, read_text_file

NAMES = ["0001.png", "caf\u00e9 2.png", "sub/0003.jpg"]
TEXT = "# a comment\n" + "\n".join(NAMES) + "\n\n"


@pytest.mark.parametrize(
    "encode",
    [
        lambda t: t.encode("utf-8"),
        lambda t: b"\xef\xbb\xbf" + t.encode("utf-8"),  # UTF-8 with a byte-order mark (Windows Notepad)
        lambda t: t.encode("utf-16"),  # BOM + little-endian
        lambda t: b"\xfe\xff" + t.encode("utf-16-be"),
        lambda t: t.encode("utf-32"),
        lambda t: t.replace("\n", "\r\n").encode("utf-8"),  # CRLF line ends
        lambda t: b"\xef\xbb\xbf" + t.replace("\n", "\r\n").encode("utf-8"),
    ],
    ids=["utf8", "utf8-bom", "utf16-le-bom", "utf16-be-bom", "utf32-bom", "crlf", "bom-crlf"],
)
def test_announced_encodings_give_the_same_names(tmp_path, encode):
    path = tmp_path / "train_list.txt"
    path.write_bytes(encode(TEXT))
    assert read_split_list(path) == NAMES


@pytest.mark.parametrize(
    "data, reason",
    [
        ("0001.png\n".encode("utf-16-le"), "NUL bytes"),
        ("caf\u00e9.png\n".encode("latin-1"), "not UTF-8 (byte 0xe9 at offset 3)"),
        (b"\xff\xfe" + b"\x00\xd8\x00\x00", "utf-16"),  # a BOM, then an unpaired surrogate
    ],
    ids=["utf16-no-bom", "latin1", "broken-utf16"],
)
def test_unannounced_or_broken_encodings_are_refused_naming_the_file(tmp_path, data, reason):
    path = tmp_path / "test_list.txt"
    path.write_bytes(data)
    with pytest.raises(DataParserError, match=f"{path}.*"):
        read_text_file(path)
    with pytest.raises(DataParserError) as info:
        read_split_list(path)
    assert reason in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("hidden", ["\u200b", "\ufeff", "\u202e", "\x07"])
def test_a_name_with_an_invisible_character_is_shown_escaped_with_its_line(tmp_path, hidden):
    path = tmp_path / "train_list.txt"
    path.write_text(f"0001.png\n0002{hidden}.png\n", encoding="utf-8")
    escaped = f"\\u{ord(hidden):04x}"
    with pytest.raises(DataParserError) as info:
        read_split_list(path)
    message = str(info.value)
    assert f"{path}:2" in message and escaped in message and f"U+{ord(hidden):04X}" in message
    assert hidden not in message  # printed as is it would look like a valid name
