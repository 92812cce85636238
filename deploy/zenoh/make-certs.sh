#!/usr/bin/env bash
# Self-signed certificates and passwords for the secure Zenoh deployment (make certs; docs/deployment.md).
#
#   deploy/zenoh/make-certs.sh OUTDIR [--vehicles FILE] [IDENTITY...]
#
# Writes, with openssl only:
#   OUTDIR/ca/ca.pem, ca.key             the certificate authority (keep ca.key off every host but this one)
#   OUTDIR/router/ca.pem, router.pem, router.key, users.txt
#                                        the router's: its certificate (names: router, localhost, 127.0.0.1 and
#                                        any in ROUTER_HOSTS), and the user/password dictionary of every identity
#   OUTDIR/IDENTITY/ca.pem, cert.pem, key.pem, credentials
#                                        one directory per client: a certificate whose common name is the
#                                        identity, its key, and its user and password (one line IDENTITY:PASSWORD)
# for the identities agv-service and agv-dashboard, those of the vehicle list FILE (second column, or the
# vehicle id) and those given. An existing CA, certificate or password is kept: running it again with a new
# vehicle adds that vehicle only. Delete a file (or OUTDIR) to issue it again (docs/deployment.md, rotation).
# Keys and passwords are readable by their owner only (umask 077).
set -euo pipefail

usage() { echo "usage: $0 OUTDIR [--vehicles FILE] [IDENTITY...]" >&2; exit 2; }
[ $# -ge 1 ] || usage
out=$1
shift
identities=(agv-service agv-dashboard)
while [ $# -gt 0 ]; do
    case $1 in
        --vehicles)
            [ $# -ge 2 ] || usage
            # VEHICLE_ID [IDENTITY] per line, '#' comments: the identity is the last field
            mapfile -t listed < <(sed 's/#.*//' "$2" | awk 'NF { print $NF }')
            identities+=("${listed[@]}")
            shift 2
            ;;
        -*) usage ;;
        *) identities+=("$1"); shift ;;
    esac
done

days=${CERT_DAYS:-365}
openssl=${OPENSSL:-openssl}
umask 077
mkdir -p "$out/ca" "$out/router"

# sign NAME DIR SAN: DIR/cert.pem and DIR/key.pem for common name NAME, unless they exist
sign() {
    local name=$1 key=$2 cert=$3 san=$4 usage=$5
    [ -s "$cert" ] && [ -s "$key" ] && return 0
    local ext
    ext=$(mktemp)
    printf 'basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=%s\nsubjectAltName=%s\n' \
        "$usage" "$san" >"$ext"
    "$openssl" req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout "$key" -subj "/CN=$name" \
        -out "$key.csr" 2>/dev/null
    "$openssl" x509 -req -in "$key.csr" -CA "$out/ca/ca.pem" -CAkey "$out/ca/ca.key" -CAcreateserial \
        -days "$days" -extfile "$ext" -out "$cert" 2>/dev/null
    rm -f "$key.csr" "$ext"
    echo "issued $cert (CN=$name)"
}

if [ ! -s "$out/ca/ca.pem" ] || [ ! -s "$out/ca/ca.key" ]; then
    "$openssl" req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -keyout "$out/ca/ca.key" \
        -out "$out/ca/ca.pem" -days "$days" -subj "/CN=agv-fe zenoh CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
    echo "issued $out/ca/ca.pem (a new CA: every certificate below must be issued again)"
    rm -f "$out"/router/router.pem "$out"/*/cert.pem
fi

san="DNS:router,DNS:localhost,IP:127.0.0.1"
for host in ${ROUTER_HOSTS:-}; do
    if [[ $host =~ ^[0-9.]+$|: ]]; then san+=",IP:$host"; else san+=",DNS:$host"; fi
done
cp "$out/ca/ca.pem" "$out/router/ca.pem"
sign router "$out/router/router.key" "$out/router/router.pem" "$san" serverAuth

touch "$out/router/users.txt"
declare -A done_identity=()
for identity in "${identities[@]}"; do
    [[ -n ${done_identity[$identity]:-} ]] && continue
    done_identity[$identity]=1
    if ! [[ $identity =~ ^[A-Za-z0-9_.-]{1,64}$ ]]; then
        echo "$0: invalid identity '$identity' (1 to 64 of A-Z a-z 0-9 _ . -)" >&2
        exit 2
    fi
    dir="$out/$identity"
    mkdir -p "$dir"
    cp "$out/ca/ca.pem" "$dir/ca.pem"
    sign "$identity" "$dir/key.pem" "$dir/cert.pem" "DNS:$identity" clientAuth
    if [ ! -s "$dir/credentials" ]; then
        echo "$identity:$("$openssl" rand -hex 24)" >"$dir/credentials"
    fi
    # the router's dictionary: the identity's USER:PASSWORD line, replaced when the password changed
    line=$(head -n 1 "$dir/credentials")
    grep -v "^$identity:" "$out/router/users.txt" >"$out/router/users.txt.new" || true
    echo "$line" >>"$out/router/users.txt.new"
    mv "$out/router/users.txt.new" "$out/router/users.txt"
done
echo "certificates and passwords of ${#done_identity[@]} identities in $out"
