#!/usr/bin/env bash
# Vendors OpenSeadragon (the fragment page's deep-zoom library) into the station's static files,
# so the page loads it from the station and never from a CDN (docs/web.md, "Fragment page").
#
# Usage: bash deploy/vendor-openseadragon.sh [VERSION]     (default: the version vendored now)
#
# Fetches the npm package with `npm pack` (the registry's tarball, checked by npm against the
# registry's integrity hash) into a temporary folder and copies, into
# services/web/static/vendor/openseadragon/:
#   openseadragon.min.js          the browser build the page loads
#   LICENSE.txt                   its licence (BSD-3-Clause), shipped beside it
#   openseadragon.min.js.sha256   "<sha256>  openseadragon.min.js", what
#                                 tests/web/test_security_claims.py checks the served file against
#   VERSION                       the npm version
# Commit the four files. The viewer (static/viewer/viewer.js) is written against OpenSeadragon 6's
# DrawerBase / TileSource API: after a major version change, run tests/web/test_fragment_page.py
# and tests/web/test_shader_parity.py; the page's CSP allows the one inline style OpenSeadragon
# injects by its hash (services/web/__init__.py, OPENSEADRAGON_STYLE_HASH: the test of that name says
# the new one when the style changed).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dest="$here/services/web/static/vendor/openseadragon"
version="${1:-$(cat "$dest/VERSION" 2>/dev/null || echo 6.1.1)}"

command -v npm >/dev/null || { echo "npm is needed (apt-get install -y npm)" >&2; exit 1; }
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "openseadragon@$version" >/dev/null)
tar -xzf "$tmp"/openseadragon-*.tgz -C "$tmp"
got="$(sed -n 's/^ *"version": *"\([^"]*\)".*/\1/p' "$tmp/package/package.json" | head -n 1)"
[ "$got" = "$version" ] || { echo "npm gave version $got, not $version" >&2; exit 1; }

mkdir -p "$dest"
install -m 644 "$tmp/package/build/openseadragon/openseadragon.min.js" "$dest/openseadragon.min.js"
install -m 644 "$tmp/package/LICENSE.txt" "$dest/LICENSE.txt"
(cd "$dest" && sha256sum openseadragon.min.js > openseadragon.min.js.sha256)
echo "$version" > "$dest/VERSION"
echo "vendored OpenSeadragon $version into $dest:"
cat "$dest/openseadragon.min.js.sha256"
