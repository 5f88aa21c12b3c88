#!/usr/bin/env bash
# Download Debian's OpenArena data packages (GPL-2+, see the copyright files this
# unpacks under data/game/doc/) and unpack their .pk3 archives into data/game/
# (or $JTUS_GAME_ASSETS). Needs apt-get (no root: packages are downloaded, not
# installed) and about 300 MB of disk. Nothing here is committed.
#
#   bash data/fetch_game_assets.sh
#   python -m jtus.sim levels
set -euo pipefail
dest="${JTUS_GAME_ASSETS:-$(cd "$(dirname "$0")" && pwd)/game}"
pkgs="openarena-data openarena-081-maps openarena-081-textures openarena-081-misc openarena-085-data openarena-oacmp1"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
if ! apt-get download $pkgs; then
  echo "error: apt-get download failed; run 'apt-get update' (as root) and try again" >&2
  exit 2
fi
for deb in *.deb; do dpkg-deb -x "$deb" root; done
mkdir -p "$dest.tmp/doc"
find root -name '*.pk3' -path '*baseoa*' -exec cp {} "$dest.tmp/" \;
for p in $pkgs; do cp "root/usr/share/doc/$p/copyright" "$dest.tmp/doc/$p.copyright"; done
rm -rf "$dest"
mv "$dest.tmp" "$dest"
echo "unpacked $(ls "$dest"/*.pk3 | wc -l) archives into $dest"
