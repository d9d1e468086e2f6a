#!/bin/sh
# TLS certificates of a fleet's Zenoh router (zenoh-router.json5) and of its members.
#
#   ROUTER_NAME=router.fleet.lan sh make-certs.sh DIR [MEMBER ...]
#
# DIR receives ca.pem (the fleet's certificate authority) and ca-key.pem (made once, reused
# by later runs to add members), router-cert.pem and router-key.pem for the host name
# ROUTER_NAME (the name the members connect to), and NAME-cert.pem, NAME-key.pem for each
# MEMBER (default: ins-health uav-1 ground-station). A member's name is its certificate's
# common name, which the router's access control matches (cert_common_names): a vehicle's is
# its vehicle id. Keys are 0600.
set -eu
dir=${1:?usage: ROUTER_NAME=host sh make-certs.sh DIR [MEMBER ...]}
shift
[ $# -gt 0 ] || set -- ins-health uav-1 ground-station
router=${ROUTER_NAME:?set ROUTER_NAME to the host name the members connect to}
days=825
umask 077
mkdir -p "$dir"
cd "$dir"

# P-256 keys; X.509 v3 with the extensions rustls (Zenoh's TLS) requires of every certificate.
sign() { # sign NAME EXTENSIONS: NAME-key.pem, NAME-cert.pem signed by the CA
    openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$1" \
        -keyout "$1-key.pem" -out "$1.csr"
    printf '%s\n' "$2" >"$1.ext"
    openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial \
        -days "$days" -extfile "$1.ext" -out "$1-cert.pem"
    rm -f "$1.csr" "$1.ext"
    chmod 644 "$1-cert.pem"
}

if [ ! -f ca.pem ]; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 \
        -subj "/CN=ins-health fleet CA" -keyout ca-key.pem -out ca.pem
    chmod 644 ca.pem
fi
if [ ! -f router-cert.pem ]; then
    sign router "basicConstraints=CA:FALSE
subjectAltName=DNS:$router
extendedKeyUsage=serverAuth"
fi
for member in "$@"; do
    sign "$member" "basicConstraints=CA:FALSE
subjectAltName=DNS:$member
extendedKeyUsage=clientAuth"
done
ls -l "$PWD"
