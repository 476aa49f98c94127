#!/bin/sh
# sh make-certs.sh DIR NAME...: a throw-away certificate authority (DIR/ca.pem) and, for each
# NAME, DIR/NAME/{ca.pem,node.pem,node.key}: a certificate with common name NAME for a router
# joined to the others over tls/ (docs/deployment.md). Run each router from a folder holding
# its three files and service.json5. SAN (default "IP:127.0.0.1,DNS:localhost") must name the
# addresses the other routers connect to. For trials: a real fleet's CA key stays offline.
set -e
dir=$1
shift
san=${SAN:-IP:127.0.0.1,DNS:localhost}
mkdir -p "$dir"
openssl req -x509 -newkey rsa:2048 -nodes -keyout "$dir/ca.key" -out "$dir/ca.pem" -days 30 \
  -subj "/CN=gpbf-trial-ca" 2>/dev/null
for name in "$@"; do
  mkdir -p "$dir/$name"
  printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth,clientAuth\n' \
    "$san" > "$dir/$name/ext.cnf"
  openssl req -newkey rsa:2048 -nodes -keyout "$dir/$name/node.key" -out "$dir/$name/node.csr" \
    -subj "/CN=$name" 2>/dev/null
  openssl x509 -req -in "$dir/$name/node.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" \
    -CAcreateserial -out "$dir/$name/node.pem" -days 30 -extfile "$dir/$name/ext.cnf" 2>/dev/null
  cp "$dir/ca.pem" "$dir/$name/ca.pem"
  rm "$dir/$name/node.csr" "$dir/$name/ext.cnf"
done
