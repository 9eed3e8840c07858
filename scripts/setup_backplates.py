#!/usr/bin/env python3
"""Fetch a bank of free-licensed backplate photographs for `background.kind: images`.

    python scripts/setup_backplates.py [--out DIR] [--force]     (DIR: ~/.cache/blsm-synth/backplates)

Sources: pinned Debian (bookworm) packages only, fetched with `apt-get download PKG=VERSION` and
unpacked with `dpkg-deb -x` (PyPI `pip download --no-deps` and `npm pack` entries are supported, none
is pinned now): scratch (Scratch 1.4 backgrounds, CC-BY-SA-3.0); gcompris-qt-data (photographs of
its "explore_monuments" and "details" activities, read out of the Qt .rcc bundles, CC0 / public
domain / CC-BY(-SA) per the README beside each image); lomiri-wallpapers-16.04 (CC-BY-4.0);
lxqt-themes (LGPL-2.1+); mate-backgrounds (GPL-2+); plasma-workspace-wallpapers (GPL-2+ per
debian/copyright, LGPL-3 per metadata.json); tuxpaint-data (photo templates, GPL-2+).

Licence policy: a photograph is kept only where the package's usr/share/doc/PKG/copyright (or the
README shipped with the GCompris image) states a free licence for it: CC0, public domain, CC-BY,
CC-BY-SA, GPL/LGPL. Left out: GFDL-only images (gimp-help-en, palapeli's castle), sample images
whose licence the copyright file does not name (opencv-doc, scikit-image), artwork, renders,
abstract wallpapers, photos dominated by people, and the reserved kphotoalbum, sports2d, pose2sim.
SOURCES.md lists licence and author per file: keep it with the pictures (CC-BY/-SA need the
attribution; -SA and GPL need modified copies under the same licence).

Each file is checked against its sha256, converted to JPEG (longer side <= 1024 px) when Pillow is
importable (else copied as is) and written as OUT/<source>_<name>.jpg, with plates.json (per file:
package, version, original path, licence, author, scene indoor/outdoor, horizon = image row of the
horizon, or indoors of the eye-level vanishing line, as a fraction of the height from the top,
estimated by eye; null where no ground shows) and SOURCES.md. Built in a temporary folder and
renamed into place; a rerun with the same table does nothing. On failure: one line, exit status 2.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import shutil
import struct
import subprocess
import sys
import tarfile
import tempfile
import time
import warnings
import zipfile
import zlib
from pathlib import Path

try:
    from PIL import Image, ImageOps
except ImportError:  # copy the originals as they are
    Image = ImageOps = None

# key: (registry, package, version, folder in the package, default licence, default author)
SOURCES = {
    "scratch": ("deb", "scratch", "1.4.0.6~dfsg1-6.1", "usr/share/scratch/Media/Backgrounds/",
                "CC-BY-SA-3.0", "MIT Scratch team"),
    "gcompris": ("deb", "gcompris-qt-data", "3.1-2", "usr/share/gcompris-qt/rcc/", "", ""),
    "lomiri16": ("deb", "lomiri-wallpapers-16.04", "20.04.0-2", "usr/share/backgrounds/", "", ""),
    "lxqt": ("deb", "lxqt-themes", "1.2.0-1", "usr/share/lxqt/wallpapers/", "LGPL-2.1+", "LXQt team"),
    "mate": ("deb", "mate-backgrounds", "1.26.0-1", "usr/share/backgrounds/mate/nature/", "GPL-2+",
             "2008, Sergey Nazarov"),
    "plasma": ("deb", "plasma-workspace-wallpapers", "4:5.27.5-2", "usr/share/wallpapers/",
               "GPL-2+ (debian/copyright); LGPL-3 (metadata.json)", ""),
    "tuxpaint": ("deb", "tuxpaint-data", "1:0.9.28-sdl2-1", "usr/share/tuxpaint/templates/", "GPL-2+",
                 "Bill Kendrick and Tux Paint contributors"),
}
# GCompris entries name "bundle!member": member of usr/share/gcompris-qt/rcc/<bundle>.rcc
RCC_PREFIX = {"explore_monuments": "gcompris/src/activities/explore_monuments/resource/",
              "details": "gcompris/src/activities/details/resource/image/"}

# ruff: noqa: E501  (the table rows below carry a sha256 and an attribution each)
# source|path in the package|name|in/out|horizon (fraction of height, "" = none)|sha256|licence|author
PLATES = """
scratch|Indoors/chalkboard.jpg|chalkboard|in|0.55|d3c3510686181920c83c9cf29c3579a9dc33a0a694833afed66fa9de2becce09||
scratch|Indoors/clothing-store.jpg|clothing-store|in|0.45|1f0cce2cb9743d7e41fde7cc66d95371ff77a48d0b29c84bcfd3170d25ba8106||
scratch|Indoors/hall.jpg|hall|in|0.5|31320a5aa739d6dbcf7339e9885e44a26375cb805972d8ccd2fb55af2dff2b93||
scratch|Indoors/kitchen.jpg|kitchen|in|0.42|b50e1cdc7cac868af8f07e85f1c2e10b40c351337ca5ab8e27577600d5c8b5b4||
scratch|Indoors/the-movies-inside.jpg|the-movies-inside|in|0.5|f567d8e0b693effb6c7e749ffc488acd8dc38641d0250daea11d09ca58588ae5||
scratch|Nature/beach-malibu.jpg|beach-malibu|out|0.38|13ecd1022ff35a5d817054ccf86749bc7229b990da104e00cbe74b15daff7a1b||
scratch|Nature/canyon.jpg|canyon|out|0.42|f63f68845f52993ad24748f559d29d09fed4ad62a56681df98b3db3a13a0c34c||
scratch|Nature/forest.jpg|forest|out|0.55|c4176201e98934611b1b31270897fc23c82c55f9a59b81af75cf6b0c2757e54c||
scratch|Nature/garden-rock.jpg|garden-rock|out|0.15|5beb88e795dc1e25d4aee44e344c31c1b8c456234c6ae3c4dbfd9d46b8a9a813||
scratch|Nature/grand-canyon.jpg|grand-canyon|out|0.38|f121a138f0eb7645752c201c3318065fc2ea1e50272bfbd878531037b00c08c2||
scratch|Nature/gravel-desert.jpg|gravel-desert|out|0.45|54d7b2308eb4e6d5f86aed23d9b434f46553ed711219933311ed97950b722ec9||
scratch|Nature/hill.jpg|hill|out|0.3|9c41784b792b117b032f0054e1c00371d4dae5cd077b8b805d099e355cdad8e9||
scratch|Nature/lake.jpg|lake|out|0.5|398c72f0bfb8d6f5cf25b00d046201868fbec33c3e7a3e713f50c3f427d45539||
scratch|Nature/pathway.jpg|pathway|out|0.5|a26c8ebd2305c20b2ba1524313d0cbf85229ec3c9fab72e58056a83c74e9b6a0||
scratch|Outdoors/all-sports-mural.jpg|all-sports-mural|out|0.45|65e7285b2671bdcf9a13ddca77aa8c7055a315d69a6412ab80a7d5847472404c||
scratch|Outdoors/atom-playground.jpg|atom-playground|out|0.15|b4c35a6c9d5e5243df537dd674d784e9f8944308a2ce77cc4e4dce49b2c5ca94||
scratch|Outdoors/bench-with-view.jpg|bench-with-view|out|0.25|b3cf022ad65e8b0fe837214bedf378532a068e19a0bb28081ec255adc4341170||
scratch|Outdoors/berkeley-mural.jpg|berkeley-mural|out|0.5|8f3be0fed57b890d43db53da9feda54ac9b5f99e6c69846a9503571af1cef1d3||
scratch|Outdoors/boardwalk.jpg|boardwalk|out|0.55|5a004a91d9dee2324a9df6d828b9c6b64229442530d8bc7e627b1a909a121146||
scratch|Outdoors/brick-wall-and-stairs.jpg|brick-wall-and-stairs|out|0.45|2a0d7d1f1244d25debe2a7a9b023174976ec5d50c117c55efee15da6df87cf41||
scratch|Outdoors/brick-wall2.jpg|brick-wall2|out|0.5|cd0c5295a31f0d2d48dd3229c339abbe56d9b9c5bf4e90d06383aa912de4dd7d||
scratch|Outdoors/building-at-mit.jpg|building-at-mit|out|0.57|72724d90df71e8340b59d9199b736a839582d4145c94a730b663cf9ad3d6941e||
scratch|Outdoors/building-fireproof.jpg|building-fireproof|out|0.7|37b8f49b1f7cb465f64e4669718eec92e7fca7c0e9724c7b228ff59cef432673||
scratch|Outdoors/castle.jpg|castle|out|0.75|5486402c0ff5e01236cade4794449ca8243f5b7555af10f9a1aeb247525a91e0||
scratch|Outdoors/driveway.jpg|driveway|out|0.5|d68a17363238af3667767d2675bace26b4c92249eacb15c4a922890f4665ee5b||
scratch|Outdoors/hallway_outdoors.jpg|hallway-outdoors|out|0.52|1755e187137833c431360ad76e94ec5677b984e07925bbca7f5be4b3c41a5c79||
scratch|Outdoors/hay_field.jpg|hay-field|out|0.45|2c3559b215100bafcae23b7aeefaaa09b40b013b7facd5b716ca92ef81bc06df||
scratch|Outdoors/houses.jpg|houses|out|0.45|e06f499ea6830d58e954a63dc067abff595156a283f14a720400a1ddf121e870||
scratch|Outdoors/mansion.jpg|mansion|out|0.58|7b3ef7facbf7c44d97c610d13e314e3b6adf93f8edcaf5b7a6d942190f319797||
scratch|Outdoors/parking-ramp.jpg|parking-ramp|out|0.5|2e147b79b03a7565cf082d4ffd91c8cdd6c381b7100c406b643b6b95035366ea||
scratch|Outdoors/pool.jpg|pool|out|0.3|66cbb0c5625e886afa3981e5a46c5ac33252e362ed48cdd02e7520877323afcd||
scratch|Outdoors/route66.jpg|route66|out|0.45|9202a27db67f8758e5528dcc7438ce42d53c9f33619fb1634ada6ceda3a01204||
scratch|Outdoors/silos.jpg|silos|out|0.6|837a55b821784c352cd7dd8f89cfee93565e4978d70b6c8968504ed6e5c84376||
scratch|Outdoors/the-movies.jpg|the-movies|out|0.4|6d7702796fa6b49a701396f3f8fc7b6d060a987caf9c0b1d5d74f65b60b9e5de||
scratch|Outdoors/train-tracks1.jpg|train-tracks1|out|0.4|8780a22be05ddd1baf7aff86adf43d60f063a042daf5da1194183ed2b4cf38a1||
scratch|Outdoors/train-tracks2.jpg|train-tracks2|out|0.1|fdfdbf4c24b5c1060befd6bcad408fd6456c8479ee570c2760e9da9b8f906d24||
scratch|Outdoors/village.jpg|village|out|0.45|a6b20f4ada48f55837db5db53b006fe41b3a33913bcdf98f4bced666a453c838||
scratch|Outdoors/wooden-house.jpg|wooden-house|out|0.6|b82433d2d54ee0e3cd8b80a109355999f9800f8bef1d78b9531297721ebe9f4b||
scratch|Sports/basketball-court1-a.jpg|basketball-court1-a|out|0.2|22246a0a06249699126e9c7926b2d1bcac26b4383785442d512aff38646872ca||
scratch|Sports/basketball-court1-b.jpg|basketball-court1-b|out|0.3|f499f2dd9ca1c9bd5815e2981a644ca34f542300edbc0289accb803819792516||
scratch|Sports/playing-field.jpg|playing-field|out|0.35|bee22943bceb3e8b654f4a15e8467cb6ca32f91a6971a8e7a0b055678376eaec||
scratch|Sports/tennis-backboard.jpg|tennis-backboard|out|0.3|dee231ff34eccfd7847ccd52dc05a5fc005ad317352a42f6160200dfaa61a49a||
gcompris|explore_monuments!egypt/bentPyramid.webp|bent-pyramid|out|0.6|ca717a088d790a901ffa1b03162c5cc438f99924d457f988263f158a7cc2cb38|Public Domain|Neithsabes; https://commons.wikimedia.org/wiki/File:Pyramide_rhomboidale_01.JPG
gcompris|explore_monuments!egypt/greatPyramidOfGiza.webp|great-pyramid-of-giza|out|0.88|f8427c09579493e7918d00134423ed40140c2f3fa09fb13341d3c1a0640fc1e9|CC0-1.0|Gary Todd; https://commons.wikimedia.org/wiki/File:Giza_Great_Pyramid_of_Khufu_(9793952173).jpg
gcompris|explore_monuments!egypt/meidumPyramid.webp|meidum-pyramid|out|0.62|694a4eaebc52849aacf802383bc5c755c0fff97b8342a4ef733c7a36c6e6aa53|Public Domain|Neithsabes; https://commons.wikimedia.org/wiki/File:Meidoum_pyramide_006.JPG
gcompris|explore_monuments!egypt/redPyramid.webp|red-pyramid|out|0.6|7df87dfe904e18fee2062e8dba2cbfc5c7b807e27c688b271a7380000865c2cf|Public Domain|Chipdawes; https://commons.wikimedia.org/wiki/File:RedPyramid.JPG
gcompris|explore_monuments!france/arlesAmphitheater.webp|arles-amphitheater|out|0.72|62d80a80ca5e5040bdb87c6f2fb57fa333d9b190c9a41066e4017cd4268656d9|Public Domain|(WT-fr) OT Arles; https://commons.wikimedia.org/wiki/File:Arenes_arles.JPG
gcompris|explore_monuments!france/chateaudeChambord.webp|chateaude-chambord|out|0.6|a96693bfff66c9a747a066b8d798aaf876427de969603c4125bf881f8af0ac2d|Public Domain|BjörnT; https://commons.wikimedia.org/wiki/File:Chambord_Frontansicht.JPG
gcompris|explore_monuments!france/chateaudeChenonceau.webp|chateaude-chenonceau|out|0.6|4e414fc35ae9b4e18e3219d6278287fb720e89facd332fef9a1c4fe9c3c3adc3|Public Domain|Alf van Beem; https://commons.wikimedia.org/wiki/File:Ch%C3%A2teau_de_Chenonceau_photo_1.JPG
gcompris|explore_monuments!france/citedeCarcassonne.webp|citede-carcassonne|out|0.6|b9de4b334e76df53df948de034f4bcc744be682a904ad7c61a9f9f7ac8de326b|Public Domain|Petitemontagnedujura; https://commons.wikimedia.org/wiki/File:Carcassonne_-_la_Cit%C3%A9.jpg
gcompris|explore_monuments!france/eiffelTower.webp|eiffel-tower|out|0.82|cf115ede228937f0dfea0ffd7efa5fa24a948f388091ce1a123e7636b25c080b|Public Domain|Tognopop; https://commons.wikimedia.org/wiki/File:Eiffel_Tower_20051010.jpg
gcompris|explore_monuments!france/montStMichel.webp|mont-st-michel|out|0.52|1c097b958c4bc0e52384e572c3e3ed70abbb54e9b4936cd0852320e1ce12561e|CC0-1.0|Ali Sabbagh; https://commons.wikimedia.org/wiki/File:Mont_Saint-Michel_IMG_5109_(48875955288).jpg
gcompris|explore_monuments!france/palaisdesPapes.webp|palaisdes-papes|out|0.82|fded6367850d2fafaf5ecad961ba51efbdc0c3d3171f7cc058d2ccfd2e6897e6|CC0-1.0|Tognopop; https://commons.wikimedia.org/wiki/File:Main_entrance_of_the_Palais_des_Papes_-_20050823.jpg
gcompris|explore_monuments!france/reimsCathedral.webp|reims-cathedral|out|0.9|720ddce0a3124d68e306008c152fb19ec2a2917b3609ba8a31607cffaf52c2d2|Public Domain|Mattana; https://commons.wikimedia.org/wiki/File:Reims_Cathedrale_Notre_Dame_002_chevet.JPG
gcompris|explore_monuments!germany/aulaPalatina.webp|aula-palatina|out|0.82|5b39680425fca3ff5f56b3bd79d11683a46a009d66ef23445e165ea72524b3cb|Public Domain|Berthold Werner; https://commons.wikimedia.org/wiki/File:Trier_Konstantinbasilika_BW_1.JPG
gcompris|explore_monuments!germany/berlinCathedral.webp|berlin-cathedral|out|0.82|b552994f64727ceaa04218d6a5e7a86b08cb8b550c1eeae0b010f857286d308e|CC0-1.0|Gary Todd; https://commons.wikimedia.org/wiki/File:Berlin_Cathedral_(28668994926).jpg
gcompris|explore_monuments!germany/brandenburgGate.webp|brandenburg-gate|out|0.8|2cb312c79a20e0cd8ed865c5b15a95af86d8d95a0ab96da8814c073857abf4bb|Public Domain|Evans1551; https://commons.wikimedia.org/wiki/File:Brandenburg_Gate_(summer_2005).JPG
gcompris|explore_monuments!germany/schwerinPalace.webp|schwerin-palace|out|0.78|91be8dd19821221b2b3c30a78cb43a17d8017751a1d36acd751b1e9417acbbae|CC0-1.0|Hermann Luyken; https://commons.wikimedia.org/wiki/File:2012.02.26.121724_Schloss_Schwerin.jpg
gcompris|explore_monuments!germany/trierImperialBaths.webp|trier-imperial-baths|out|0.58|dd1818360d153c095e227157d128e498fe9b29437594e8e5c663184cad4120fb|Public Domain|Berthold Werner; https://commons.wikimedia.org/wiki/File:Trier_Kaiserthermen_BW_1.JPG
gcompris|explore_monuments!germany/wormsCathedral.webp|worms-cathedral|out|0.88|c90cdcbf981bcd5f118b553b059448db6fb0bfe801b40240e02ccd2975b92a59|Public Domain|Immanuel Giel; https://commons.wikimedia.org/wiki/File:Dommodell_Worms_04.jpg
gcompris|explore_monuments!india/gatewayofIndia.webp|gatewayof-india|out|0.75|8d1053776a85a9703f819ae6a82f981cbfa9a8961712404afee235afd87a0e48|CC0-1.0|Simon Steinberger; https://commons.wikimedia.org/wiki/File:Gateway-of-India.jpg
gcompris|explore_monuments!india/greatStupa.webp|great-stupa|out|0.6|3b6741152471d00646271d3a413c08af0533766f09dc87af19abb9ff71801886|Public Domain|ArnoldBetten; https://commons.wikimedia.org/wiki/File:Sanchi_Stupa_1_(1999).JPG
gcompris|explore_monuments!india/konarkSunTemple.webp|konark-sun-temple|out|0.6|c94ddb83bb2d878fecaf0677e8e6c1e73ede7dd39bd69f5e84d2f68e84515156|Public Domain|Tetraktys; https://commons.wikimedia.org/wiki/File:Konark_Sun_Temple_Front_view.jpg
gcompris|explore_monuments!india/mysorePalace.webp|mysore-palace|out|0.7|a84a26be8d9447341e5235dd319acc71a49f2d91c8dd55a17a89867c64a580c0|Public Domain|Shiva sg; https://commons.wikimedia.org/wiki/File:Mysore_Palace_2006.jpg
gcompris|explore_monuments!india/rangGhar.webp|rang-ghar|out|0.75|41791947f8772c9bf483ddb13a4fa4dfbbd1eef44f29937a99eebc5361d981a2|Public Domain|Porikolpok Oxom; https://commons.wikimedia.org/wiki/File:Rangghar_Assam.JPG
gcompris|explore_monuments!india/victoriaMemorial.webp|victoria-memorial|out|0.68|be7b3264cd3391e5b50714e0cec31f2e23e658498b5aba584a4b9aaf526dc51e|CC0-1.0|Anourag; https://commons.wikimedia.org/wiki/File:Victoria_Memorial_Calcutta.jpg
gcompris|explore_monuments!usa/fortSumter.webp|fort-sumter|out|0.27|42c8376f99f770fa9daa92afb8cde44dc58dd3282b10c5ba8fabec02ea4b9643|CC0-1.0|Gary Todd; https://commons.wikimedia.org/wiki/File:Fort_Sumter,_South_Carolina_(12583090893).jpg
gcompris|explore_monuments!usa/georgeWashingtonBirthplace.webp|george-washington-birthplace|out|0.75|134f44b0e1c333202da337c73b6752db36fcbb5cb73e05cfcb4e5f4ff2fb4f43|Public Domain|National Park Service; https://commons.wikimedia.org/wiki/File:George_Washington_Birthplace_National_Monument,_Virginia_(e1c27488-14f6-4478-ab87-d36af60e34d3).jpg
gcompris|explore_monuments!wonders/chichenItza.webp|chichen-itza|out|0.85|9882593801be435822f1d948afb36b171ed7fc7a301dfa74b11df5ea9afaf681|CC-BY-SA 4.0|Daniel Schwen; https://commons.wikimedia.org/wiki/File:Chichen_Itza_3.jpg
gcompris|explore_monuments!wonders/colosseum.webp|colosseum|out|0.75|0d38a0c2d4910f895c003825999345a86da080ff76d709bba923153cbd654945|Public Domain|Urse Ovidiu; https://commons.wikimedia.org/wiki/File:Colosseum_Roma_2009.jpg
gcompris|explore_monuments!wonders/greatWallofChina.webp|great-wallof-china|out|0.3|546e2483d17c2b732ce375d946afba6fc612166abcd6d976217747a982b60777|CC0-1.0|Nicolas Perrault III; https://commons.wikimedia.org/wiki/File:Great_Wall_of_China_July_2006.JPG
gcompris|explore_monuments!wonders/petra.webp|petra|out|0.9|cc782ccdd5b508299ad17402df2d0d375c26e1f9b18e4d2e6c3fd474fcaeb458|Public Domain|Berthold Werner; https://commons.wikimedia.org/wiki/File:Petra_Jordan_BW_36.JPG
gcompris|explore_monuments!wonders/tajMahal.webp|taj-mahal|out|0.6|fc0d45ec5a258568858c70d2d78eb23a5eb769255d74b384f70c20422d2eb351|CC-BY-SA 4.0|Yann; https://commons.wikimedia.org/wiki/File:Taj_Mahal,_Agra,_India.jpg
gcompris|details!FanoeWindmill_background.webp|fanoe-windmill|out|0.85|3cea5251d1e93a9a2e03d3d6001a26098c9614e4b7922725924307a305148068|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Cnyborg, license CC-BY-SA 3.0, source at https://commons.wikimedia.org/wiki/File:DK_Fanoe_Windmill01.JPG
gcompris|details!GizahPyramids_background.webp|gizah-pyramids|out|0.6|71946fdfe1a1dab7b081b97a53fe4d2beed6eaf8bf02e0df7ecf4a1974bbe7db|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Ricardo Liberato, license CC-BY-SA 2.0, source at https://commons.wikimedia.org/wiki/File:Pyramids_at_Gizah.jpg
gcompris|details!Louvre_2007_02_24_c_background.webp|louvre-2007-02-24-c|out|0.72|cb88769524ed233f9926c75c97a8f1660c95e8284028ba142db55ea7c0fe66c2|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Benh LIEU SONG, license CC-BY-SA 3.0, source at https://commons.wikimedia.org/wiki/File:Louvre_2007_02_24_c.jpg
gcompris|details!NDP_background.webp|ndp|out|0.9|0bbfd0f6edd1145aeee774587635d7738c73274271b4be83eec9b476a3c421ee|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Sanchezn, license CC-BY-SA 3.0, source at https://commons.wikimedia.org/wiki/File:NotreDameDeParis.jpg
gcompris|details!Nagoya_background.webp|nagoya|out|0.78|84b09f2cc12c464b1404e4fdb3c45ac7f7f51e9b4b3dfe450bf7cdf669946cd7|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Base64, license CC-BY-SA 3.0, source at https://commons.wikimedia.org/wiki/File:Nagoya_Castle(Edit2).jpg
gcompris|details!TajMahal_background.webp|taj-mahal-2|out|0.7|9c2796c2a415cfd3b2ba20f52d7da5935298d00f208028b6c6d25d5d680b0cfb|CC-BY-SA 4.0|GCompris (B. Coudoin and others), from a photo by Dhirad, license CC-BY-SA 3.0, source at https://commons.wikimedia.org/wiki/File:Taj_Mahal_in_March_2004.jpg
lomiri16|aitzgorri_by_Aitzol_Berasategi.jpg|aitzgorri|out|0.5|66268e7b48f8854d36a28765fac6e23ec1aee251daa6da1f64715f201020ad36|CC-BY-4.0|Aitzol Berasategi, 2018
lomiri16|life_by_Aitzol_Berasategi.jpg|life|out|0.3|4c119350ead80201fe256850c3d316309ddfb4bdf10b235ce982dcde0c667c05|CC-BY-4.0|Aitzol Berasategi, 2018
lomiri16|picosdeeuropa_by_Aitzol_Berasategi.jpg|picosdeeuropa|out|0.3|414d0072b2f6f2c555deafeaef6e45c4fed6fa9ad26eba6560ca8803959cf97a|CC-BY-4.0|Aitzol Berasategi, 2018
lomiri16|sunset_by_Aitzol_Berasategi.jpg|sunset|out|0.45|474dab6a4b9f94dc76c29dfe30e9f5db4af0fd2e33fe5d695f8152b371efca18|CC-BY-4.0|Aitzol Berasategi, 2018
lomiri16|Wine_by_Jakkub_Mede.jpg|wine|in|0.3|d2e96e6d4da40dd804b3d0ce295e94de04a2d7d9b6785d42cd9d92ba58bced74|CC-BY-4.0|Jakub Mede, 2018
lxqt|fog.jpg|fog|out|0.45|a8235344ee6b5ab1b6de3ccef731bcc0e6509cf33ce832db87eae1eb75987083||
lxqt|this-is-not-windows.jpg|this-is-not-windows|out|0.62|2d885e0438c0ab244f818d33d8f745a1cc486558462faf9bf3948675c68ac227||
mate|Storm.jpg|storm|out|0.62|77ca53077831d3237f73393a91fc879158abc046d852941c26e90de336356957||
plasma|ColdRipple/contents/images/2560x1600.jpg|cold-ripple|out|0.5|05bef6722fc0ed81292cceb3ed026c38d17e510f3c84be7d68610c2b1a723c3f||Risto Saukonpää
plasma|EveningGlow/contents/images/2560x1600.jpg|evening-glow|out|0.4|586682dcb362b9f620068f10138f87d0d3649939aef238adc5807cb951976a7a||Ian Hex
plasma|Path/contents/images/2560x1600.jpg|path|out|0.5|7477457d7f17b736259f1b021864778ad4ba802cf3214e6728181ff29126bba8||Risto Saukonpää
tuxpaint|corn_maze.jpg|corn-maze|out|0.5|e3c5dfd777c38fbf79126795ba1165fee41e62402436196363a5e2d938a2d3be||
tuxpaint|sheep.jpg|sheep|out|0.45|cb408f8b3fc324798d012f71595a148f9fa360c17d1bde91371bd7c01e9cf881||
"""


class Failure(Exception):
    pass


def plates():
    rows = []
    for line in PLATES.strip().splitlines():
        src, path, name, scene, horizon, sha, lic, author = line.split("|")
        _, pkg, ver, base, dlic, dauthor = SOURCES[src]
        rows.append(dict(source=src, package=pkg, version=ver, path=base + path, name=name,
                         scene={"in": "indoor", "out": "outdoor"}[scene],
                         horizon=float(horizon) if horizon else None, sha256=sha,
                         licence=lic or dlic, author=author or dauthor))
    return rows


def run(cmd, cwd):
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode:
        last = (r.stderr.strip() or r.stdout.strip() or "failed").splitlines()[-1]
        raise Failure(f"{' '.join(cmd)}: {last}")


def fetch(registry, pkg, ver, work):
    """Download one pinned package into work/dl and unpack it into work/x/<pkg>; return that."""
    dl, dest = work / "dl" / pkg, work / "x" / pkg
    dl.mkdir(parents=True), dest.mkdir(parents=True)
    if registry == "deb":
        dl.chmod(0o777)  # let apt's unprivileged _apt user write there
        run(["apt-get", "download", f"{pkg}={ver}"], dl)
        run(["dpkg-deb", "-x", str(next(dl.glob("*.deb"))), str(dest)], dl)
    elif registry == "pip":
        run([sys.executable, "-m", "pip", "download", "--no-deps", "-d", ".", f"{pkg}=={ver}"], dl)
        f = next(dl.iterdir())
        (zipfile.ZipFile(f) if f.suffix in (".whl", ".zip") else tarfile.open(f)).extractall(dest)
    elif registry == "npm":
        run(["npm", "pack", f"{pkg}@{ver}"], dl)
        tarfile.open(next(dl.glob("*.tgz"))).extractall(dest)
    return dest


def rcc_member(buf, want):
    """One file from a Qt resource bundle (.rcc, format 1-3; zlib-compressed or stored)."""
    magic, ver, tree, data, names = struct.unpack(">4sIIII", buf[:20])
    if magic != b"qres":
        raise ValueError("not a Qt .rcc file")
    size = 14 if ver == 1 else 22

    def name(off):
        n, = struct.unpack(">H", buf[names + off:names + off + 2])
        return buf[names + off + 6:names + off + 6 + 2 * n].decode("utf-16-be")

    node, parts = 0, want.split("/")
    for part in parts:
        p = tree + node * size
        flags, count, first = struct.unpack(">HII", buf[p + 4:p + 14])
        if not flags & 2:
            raise KeyError(want)
        node = next((c for c in range(first, first + count)
                     if name(struct.unpack(">I", buf[tree + c * size:tree + c * size + 4])[0]) == part), None)
        if node is None:
            raise KeyError(want)
    p = tree + node * size
    flags, = struct.unpack(">H", buf[p + 4:p + 6])
    off, = struct.unpack(">I", buf[p + 10:p + 14])
    n, = struct.unpack(">I", buf[data + off:data + off + 4])
    blob = buf[data + off + 4:data + off + 4 + n]
    return zlib.decompress(blob[4:]) if flags & 1 else blob


def read_plate(root, plate):
    if "!" in plate["path"]:
        bundle, member = plate["path"].split("!")
        prefix = RCC_PREFIX[Path(bundle).name]
        plate["path"] = f"{bundle}.rcc!{prefix}{member}"
        return rcc_member((root / f"{bundle}.rcc").read_bytes(), prefix + member)
    return (root / plate["path"]).read_bytes()


def write_plate(data, plate, bank):
    stem = f"{plate['source']}_{plate['name']}"
    if Image is None:
        dest = bank / (stem + Path(plate["path"]).suffix.lower())
        dest.write_bytes(data)
        return dest.name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        im = ImageOps.exif_transpose(Image.open(io.BytesIO(data))).convert("RGB")
    im.thumbnail((1024, 1024), Image.LANCZOS)
    im.save(bank / (stem + ".jpg"), "JPEG", quality=90, optimize=True)
    plate["width"], plate["height"] = im.size
    return stem + ".jpg"


def sources_md(table):
    lines = ["# Backplate photographs", "",
             "Written by scripts/setup_backplates.py from pinned Debian packages. Keep this file with the",
             "pictures: CC-BY / CC-BY-SA need the attribution below; -SA and GPL/LGPL need modified",
             "copies under the same licence. `horizon` (in plates.json) is estimated by eye.", "",
             "| file | package | version | original path | licence | author / source |",
             "| --- | --- | --- | --- | --- | --- |"]
    for f, p in table.items():
        cells = [f, p["package"], p["version"], p["path"], p["licence"], p["author"] or "(not stated)"]
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="~/.cache/blsm-synth/backplates", help="bank folder")
    ap.add_argument("--force", action="store_true", help="rebuild even if the bank is up to date")
    args = ap.parse_args(argv)
    out = Path(args.out).expanduser().resolve()
    rows = plates()
    stamp = hashlib.sha256(f"{PLATES}{SOURCES}{Image is not None}".encode()).hexdigest()
    by_pkg = {}
    for r in rows:
        by_pkg.setdefault((r["source"],) + SOURCES[r["source"]][:3], []).append(r)
    try:
        done = json.loads((out / "plates.json").read_text()) if (out / ".stamp").read_text() == stamp else {}
    except (OSError, ValueError):
        done = {}
    if done and all((out / f).is_file() for f in done) and not args.force:
        for (_, _, pkg, ver), rs in by_pkg.items():
            print(f"{pkg}={ver}: {len(rs)} plates, up to date")
        return 0
    t0 = time.time()
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".backplates-", dir=out.parent))
    try:
        bank, table = work / "bank", {}
        bank.mkdir()
        for (_, registry, pkg, ver), rs in by_pkg.items():
            what = f"{pkg}={ver}"
            try:
                root = fetch(registry, pkg, ver, work)
                for plate in rs:
                    what = f"{pkg}={ver}: {plate['path']}"
                    data = read_plate(root, plate)
                    if hashlib.sha256(data).hexdigest() != plate["sha256"]:
                        raise Failure("sha256 mismatch")
                    fname = write_plate(data, plate, bank)
                    table[fname] = {k: v for k, v in plate.items() if k != "name"}
            except Failure as e:
                raise Failure(f"{what}: {e}") from None
            except (OSError, ValueError, KeyError, StopIteration, subprocess.SubprocessError) as e:
                raise Failure(f"{what}: {type(e).__name__}: {e}") from None
            kinds = sorted({p["licence"] for p in rs})
            print(f"{pkg}={ver}: {len(rs)} plates ({'; '.join(kinds)})", flush=True)
        (bank / "plates.json").write_text(json.dumps(table, indent=1, ensure_ascii=False) + "\n")
        (bank / "SOURCES.md").write_text(sources_md(table))
        (bank / ".stamp").write_text(stamp)
        if out.exists():
            out.rename(work / "old")
        bank.rename(out)
    except Failure as e:
        print(f"setup_backplates: failed: {e}", file=sys.stderr)
        return 2
    finally:
        shutil.rmtree(work, ignore_errors=True)
    n_in = sum(p["scene"] == "indoor" for p in table.values())
    print(f"{out}: {len(table)} plates ({n_in} indoor) in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
