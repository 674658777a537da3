#!/usr/bin/env bash
# Generate every platform's key pair and the federation's trust file into
# deploy/config/keys/, and the TLS certificates and passwords into deploy/config/keys/tls/
# (make_certs.py; openssl needed), never committed (.gitignore). Run once, before
# `docker compose up`:
#   deploy/make-keys.sh            # or: deploy/make-keys.sh /some/other/config/dir
# Uses `python -m federation.cli keys …` with PYTHON when it is set, else `dyknow keys …`
# when the CLI is on the PATH, else the project's .venv (made by `make`), else python3.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
config_dir="${1:-${here}/config}"
keys_dir="${config_dir}/keys"
trust_file="${keys_dir}/trust.json"
federation="traffic"
platforms=(uav-a uav-b uav-c operator)

root="$(cd "${here}/.." && pwd)"
if [[ -n "${PYTHON:-}" ]]; then
    keys=("${PYTHON}" -m federation.cli keys)
elif command -v dyknow >/dev/null 2>&1 && dyknow keys --help >/dev/null 2>&1; then
    keys=(dyknow keys)
elif [[ -x "${root}/.venv/bin/python" ]]; then
    keys=("${root}/.venv/bin/python" -m federation.cli keys)    # what `make` installed
else
    keys=(python3 -m federation.cli keys)
fi

mkdir -p "${keys_dir}"
chmod 700 "${keys_dir}"
for platform in "${platforms[@]}"; do
    if [[ -e "${keys_dir}/${platform}.key" ]]; then
        echo "keep ${keys_dir}/${platform}.key (exists; delete it to make a new one)"
    else
        "${keys[@]}" gen --platform "${platform}" --dir "${keys_dir}"
    fi
done
pubs=()
for platform in "${platforms[@]}"; do
    pubs+=("${keys_dir}/${platform}.pub")
done
"${keys[@]}" trust --trust-file "${trust_file}" --federation "${federation}" "${pubs[@]}"
# the hubs' access control, from the trust file (the same as shipped for these platforms)
"${PYTHON:-python3}" "${here}/make_hub_configs.py" --trust-file "${trust_file}" --out "${config_dir}"

# the zenoh links: the federation's CA, the router's and each platform's certificate
certs=()
for platform in "${platforms[@]}"; do
    certs+=(--platform "${platform}")
done
"${PYTHON:-python3}" "${here}/make_certs.py" --dir "${keys_dir}/tls" "${certs[@]}"

cat <<MSG
Keys and trust file are in ${keys_dir}, certificates and passwords in ${keys_dir}/tls.
The containers run as uid 10001 and private keys must be mode 0600, so either run
  DYKNOW_UID=\$(id -u) DYKNOW_GID=\$(id -g) docker compose -p dyknow -f deploy/docker-compose.yml up --build
or give the keys to that user: sudo chown -R 10001:10001 ${keys_dir}
MSG
