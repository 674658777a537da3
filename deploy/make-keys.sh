#!/usr/bin/env bash
# Generate every platform's key pair and the federation's trust file into
# deploy/config/keys/ (never committed: .gitignore). Run once, before `docker compose up`:
#   deploy/make-keys.sh            # or: deploy/make-keys.sh /some/other/config/dir
# Uses `dyknow keys …` when the CLI is installed, else `python -m agents.keys …`
# (the same commands; PYTHON picks the interpreter, e.g. PYTHON=.venv/bin/python).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
config_dir="${1:-${here}/config}"
keys_dir="${config_dir}/keys"
trust_file="${keys_dir}/trust.json"
federation="traffic"
platforms=(uav-a uav-b uav-c operator)

if command -v dyknow >/dev/null 2>&1 && dyknow keys --help >/dev/null 2>&1; then
    keys=(dyknow keys)
else
    keys=("${PYTHON:-python3}" -m agents.keys)
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

cat <<MSG
Keys and trust file are in ${keys_dir}.
The containers run as uid 10001 and private keys must be mode 0600, so either run
  DYKNOW_UID=\$(id -u) DYKNOW_GID=\$(id -g) docker compose -f deploy/docker-compose.yml up
or give the keys to that user: sudo chown -R 10001:10001 ${keys_dir}
MSG
