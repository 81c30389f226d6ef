#!/usr/bin/env bash
# Pack this machine's PostgreSQL 15 (Debian 12) for the device, which has none (../shared/DEVICE.md):
# the server programs the project uses, their libraries (all but glibc's and the C++ runtime), the
# share folder, UTC zone files and /opt/pgw/bin wrappers that set LD_LIBRARY_PATH. About 20 MB.
# Writes .devwheels/pgdev.tar.xz; scripts/device-scale.sh unpacks it into / there (new paths only:
# /usr/lib/postgresql/15, /usr/share/postgresql/15, /opt/pglibs, /opt/pgw) and puts /opt/pgw/bin first.
set -euo pipefail
cd "$(dirname "$0")/.."
V=15 BIN=/usr/lib/postgresql/15/bin
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/opt/pglibs" "$tmp/opt/pgw/bin" "$tmp/usr/lib/postgresql/$V/bin" "$tmp/usr/lib/postgresql/$V/lib" \
  "$tmp/usr/share/postgresql" "$tmp/usr/share/zoneinfo/Etc"
progs="postgres initdb pg_ctl psql pg_isready"
for p in $progs; do cp -a "$BIN/$p" "$tmp/usr/lib/postgresql/$V/bin/"; done
for p in $progs; do ldd "$BIN/$p"; done | awk '/=>/{print $3}' | sort -u |
  grep -v -E 'libc\.so|libm\.so|libresolv|libpthread|libdl\.so|ld-linux|libstdc\+\+|libgcc_s|librt\.so' |
  xargs -I{} cp -L {} "$tmp/opt/pglibs/"
cp -a /usr/lib/postgresql/$V/lib/*.so "$tmp/usr/lib/postgresql/$V/lib/"
cp -a /usr/share/postgresql/$V "$tmp/usr/share/postgresql/"
rm -rf "$tmp/usr/share/postgresql/$V/man"
find "$tmp/usr/share/postgresql/$V/extension" -type f ! -name 'plpgsql*' -delete
cp -L /usr/share/zoneinfo/UTC "$tmp/usr/share/zoneinfo/"; cp -L /usr/share/zoneinfo/Etc/UTC "$tmp/usr/share/zoneinfo/Etc/"
for p in $progs; do
  printf '#!/bin/sh\nexport LD_LIBRARY_PATH=/opt/pglibs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}\nexec %s/%s "$@"\n' "$BIN" "$p" \
    > "$tmp/opt/pgw/bin/$p"
  chmod 755 "$tmp/opt/pgw/bin/$p"
done
chmod -R a+rX "$tmp/opt" "$tmp/usr"
mkdir -p .devwheels
tar -C "$tmp" -cf - opt usr | xz -6 -T2 > .devwheels/pgdev.tar.xz
ls -la .devwheels/pgdev.tar.xz
