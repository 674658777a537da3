#!/usr/bin/env bash
# Generate every platform's key pair and the federation's trust file into
# deploy/config/keys/, and the TLS certificates and passwords into deploy/config/keys/tls/
# (make_certs.py; openssl needed), never committed (.gitignore). Run once, before
# `docker compose up`:
#   deploy/make-keys.sh            # or: deploy/make-keys.sh /some/other/config/dir
# Runs `python -m federation.cli keys …` with PYTHON when it is set, else with the Python
# of the `dyknow` CLI on the PATH, else the project's .venv (made by `make`), else python3:
# every command in one interpreter (each start costs a second and more on a loaded machine).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
config_dir="${1:-${here}/config}"
keys_dir="${config_dir}/keys"
trust_file="${keys_dir}/trust.json"
federation="traffic"
platforms=(uav-a uav-b uav-c operator)

root="$(cd "${here}/.." && pwd)"
cli="$(command -v dyknow || true)"
shebang="$( [[ -n "${cli}" ]] && head -n 1 "${cli}" || true)"
cli_python="${shebang#\#!}"
# only a Python named there: pip writes `#!/bin/sh` and an exec line instead when the
# interpreter's path has a space or is too long for a shebang
if [[ "${shebang}" != "#!"* || "$(basename -- "${cli_python}")" != python* \
    || ! -x "${cli_python}" ]]; then
    cli_python=""
fi
if [[ -n "${PYTHON:-}" ]]; then
    python="${PYTHON}"
elif [[ -n "${cli_python}" ]]; then
    python="${cli_python}"                   # the interpreter the CLI was installed with
elif [[ -x "${root}/.venv/bin/python" ]]; then
    python="${root}/.venv/bin/python"        # what `make` installed
else
    python=python3
fi

mkdir -p "${keys_dir}"
chmod 700 "${keys_dir}"
"${python}" - "${here}" "${config_dir}" "${keys_dir}" "${trust_file}" "${federation}" \
    "${platforms[@]}" <<'PY'
import importlib.util
import sys
from pathlib import Path

from federation.cli import main as dyknow

here, config_dir, keys_dir, trust_file, federation, *platforms = sys.argv[1:]


def run(main, args):
    """Run one command's main; stop with its exit status when it fails (as `set -e`)."""
    code = main(args)
    sys.stdout.flush()  # its lines before the next command's children (openssl) write
    if code:
        sys.exit(code)


def script(name):
    """The main of deploy/<name>.py, loaded from its file."""
    spec = importlib.util.spec_from_file_location(name, Path(here) / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.main


for platform in platforms:
    key = f"{keys_dir}/{platform}.key"
    if Path(key).exists():
        print(f"keep {key} (exists; delete it to make a new one)", flush=True)
    else:
        run(dyknow, ["keys", "gen", "--platform", platform, "--dir", keys_dir])
pubs = [f"{keys_dir}/{platform}.pub" for platform in platforms]
run(dyknow, ["keys", "trust", "--trust-file", trust_file, "--federation", federation, *pubs])
# the hubs' access control, from the trust file (the same as shipped for these platforms)
run(script("make_hub_configs"), ["--trust-file", trust_file, "--out", config_dir])
# the zenoh links: the federation's CA, the router's and each platform's certificate
certs = [arg for platform in platforms for arg in ("--platform", platform)]
run(script("make_certs"), ["--dir", f"{keys_dir}/tls", *certs])
PY

# the interpreter may not have been Python at all and made nothing without failing
for platform in "${platforms[@]}"; do
    if [[ ! -f "${keys_dir}/${platform}.key" ]]; then
        echo "make-keys.sh: no key ${keys_dir}/${platform}.key was made (with ${python});" \
            "set PYTHON to a Python that has the project installed" >&2
        exit 1
    fi
done
if [[ ! -f "${trust_file}" ]]; then
    echo "make-keys.sh: no trust file ${trust_file} was made (with ${python})" >&2
    exit 1
fi

cat <<MSG
Keys and trust file are in ${keys_dir}, certificates and passwords in ${keys_dir}/tls.
The containers run as uid 10001 and private keys must be mode 0600, so either run
  DYKNOW_UID=\$(id -u) DYKNOW_GID=\$(id -g) docker compose -p dyknow -f deploy/docker-compose.yml up --build
or give the keys to that user: sudo chown -R 10001:10001 ${keys_dir}
MSG
