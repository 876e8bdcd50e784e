#!/usr/bin/env bash
# A CA and one certificate per identity for the TLS profile (deploy/tls/README in the
# project README, "Deploying over TLS"). Every identity is its certificate's common name;
# the router's access control (router.json5) grants rights by it.
#   deploy/tls/make-certs.sh [OUT_DIR] [ROUTER_HOSTNAME...]
# OUT_DIR defaults to deploy/tls/certs; the router's certificate is valid for localhost,
# 127.0.0.1, ::1, "zenoh" and any ROUTER_HOSTNAME given (names or IP addresses).
# Writes ca.pem (+ ca.key: keep it offline), and for each of router, frontend, mapper,
# query, planner, monitor: NAME.pem and NAME.key (PKCS#8, EC P-256). Existing files are kept, so
# it is safe to run again; add an identity with IDENTITIES="planner2" deploy/tls/make-certs.sh.
set -euo pipefail
out=${1:-$(dirname "$0")/certs}
shift || true
days=${DAYS:-825}
mkdir -p "$out"
cd "$out"
umask 077

if [ ! -f ca.pem ]; then
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out ca.key
  openssl req -x509 -new -key ca.key -sha256 -days "$days" -subj "/CN=aisdf-ca" -out ca.pem \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
fi

issue() {  # issue NAME EXTENDED_KEY_USAGE SUBJECT_ALT_NAMES
  local name=$1 eku=$2 san=$3
  [ -f "$name.pem" ] && return 0
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$name.key"
  openssl req -new -key "$name.key" -subj "/CN=$name" -out "$name.csr"
  printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=%s\nsubjectAltName=%s\n' \
    "$eku" "$san" > "$name.ext"
  openssl x509 -req -in "$name.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -sha256 -days "$days" \
    -extfile "$name.ext" -out "$name.pem" 2>/dev/null
  rm -f "$name.csr" "$name.ext"
}

san="DNS:localhost,DNS:zenoh,IP:127.0.0.1,IP:::1"
for h in "$@"; do
  if [[ $h =~ ^[0-9.]+$ || $h == *:* ]]; then san="$san,IP:$h"; else san="$san,DNS:$h"; fi
done
issue router serverAuth,clientAuth "$san"
for name in frontend mapper query planner monitor ${IDENTITIES:-}; do
  issue "$name" clientAuth "DNS:$name"
done
chmod 644 ./*.pem
chmod 600 ./*.key
echo "certificates in $(pwd): $(ls ./*.pem | xargs -n1 basename | tr '\n' ' ')"
