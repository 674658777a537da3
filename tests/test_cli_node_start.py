"""What ``dyknow node`` spares at its start, and that it spares nothing a user installed.

Each case runs the node's path (through the entry point, a missing config: everything a
node runs is imported, then it exits 2) in a fresh interpreter.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]

# the node's path, then what pydantic's plugin search found and what it imported
_NODE_PATH = """
import json, sys
from federation.cli import main
assert main(["node", "-c", "no-such-config.toml"]) == 2
from pydantic.plugin._schema_validator import create_schema_validator
from pydantic.plugin._loader import get_plugins
from pydantic import BaseModel
class Late(BaseModel):
    x: int = 0
assert Late(x="1").x == 1
print(json.dumps({
    "plugins": sorted(type(p).__name__ for p in get_plugins()),
    "metadata_imported": "importlib.metadata" in sys.modules,
    "seen": sorted(sys.modules["fakeplug"].SEEN) if "fakeplug" in sys.modules else None,
}))
"""

# a pydantic plugin as a user installs one: a distribution with a ``pydantic`` entry point
_PLUGIN = """
SEEN = set()


class FakePlugin:
    def new_schema_validator(self, schema, schema_type, path, kind, config, settings):
        SEEN.add(path.name)
        return None, None, None


plugin = FakePlugin()
"""


def _node_path(extra_path: Path | None = None) -> dict[str, object]:
    """Run the node's path in a new interpreter; what it printed (`_NODE_PATH`)."""
    path = os.pathsep.join(str(p) for p in (ROOT, extra_path) if p is not None)
    done = subprocess.run(
        [sys.executable, "-c", _NODE_PATH],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": path},
        check=True,
    )
    result: dict[str, object] = json.loads(done.stdout.splitlines()[-1])
    return result


def test_without_pydantic_plugins_the_node_does_not_search_for_them() -> None:
    # no distribution declares one: the search (importlib.metadata and every
    # distribution's entry points, ~15 ms of the start) is spared, models build as ever
    found = _node_path()
    assert found == {"plugins": [], "metadata_imported": False, "seen": None}


def test_an_installed_pydantic_plugin_is_loaded_by_the_node(tmp_path: Path) -> None:
    (tmp_path / "fakeplug.py").write_text(_PLUGIN)
    info = tmp_path / "fakeplug-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: fakeplug\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[pydantic]\nfake = fakeplug:plugin\n")
    found = _node_path(tmp_path)
    assert found["plugins"] == ["FakePlugin"]
    # it saw the validators the node built at its start and those built later
    seen = found["seen"]
    assert isinstance(seen, list) and "Late" in seen and len(seen) > 1, seen


def test_the_spared_loader_has_every_name_of_pydantics_own() -> None:
    # the stand-in replaces a private module of pydantic: a new pydantic that adds a name
    # its own code reads would break the node's start, so this says so first
    from federation._cli_node import _PLUGIN_LOADER

    code = (
        "import sys, json\n"
        "from federation._cli_node import skip_pydantic_plugin_scan\n"
        "assert skip_pydantic_plugin_scan()\n"
        f"spared = set(vars(sys.modules[{_PLUGIN_LOADER!r}]))\n"
        f"del sys.modules[{_PLUGIN_LOADER!r}]\n"
        "import importlib\n"
        f"real = importlib.import_module({_PLUGIN_LOADER!r})\n"
        "own = {n for n, v in vars(real).items() if not n.startswith('__')\n"
        "       and n != 'TYPE_CHECKING'\n"
        "       and getattr(v, '__module__', real.__name__) == real.__name__\n"
        "       and not isinstance(v, type(sys))}\n"
        "print(json.dumps(sorted(own - spared)))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        check=True,
    )
    assert json.loads(done.stdout) == []


def test_what_the_search_might_find_elsewhere_counts_as_a_plugin(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # anything importlib.metadata reads that the quick look does not (a zip or an egg on
    # the path, an egg-info's entry points) keeps pydantic's own search; and whenever
    # the search finds a plugin, the quick look says so too
    from importlib.metadata import entry_points

    from federation._cli_node import no_pydantic_plugins

    def spared(*path: Path) -> bool:
        monkeypatch.setattr(sys, "path", [str(p) for p in path])
        quick = no_pydantic_plugins()
        assert not (quick and list(entry_points(group="pydantic")))
        return quick

    assert spared(tmp_path / "nothing-here")
    site = tmp_path / "site"
    info = site / "Plug-1.0.EGG-INFO"
    info.mkdir(parents=True)
    (info / "PKG-INFO").write_text("Metadata-Version: 2.1\nName: Plug\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[pydantic]\nplug = plug:plugin\n")
    assert not spared(site)
    (info / "entry_points.txt").write_text("[console_scripts]\nplug = plug:main\n")
    assert spared(site)
    zipped = tmp_path / "lib.zip"
    with zipfile.ZipFile(zipped, "w") as z:
        z.writestr("plug-1.0.dist-info/METADATA", "Metadata-Version: 2.1\nName: plug\n")
        z.writestr("plug-1.0.dist-info/entry_points.txt", "[pydantic]\nplug = plug:plugin\n")
    assert not spared(site, zipped)
    egg = tmp_path / "plug-1.0.egg"
    egg.mkdir()
    assert not spared(egg)


# the node's path, recording each dataclass of ours whose methods are generated at import
_GENERATED = """
import dataclasses, json, sys
made = []
process = dataclasses._process_class
def recording(cls, init, repr, eq, order, unsafe_hash, frozen, *rest):
    if cls.__module__.split(".")[0] in ("agents", "dyknow_core", "ontology", "federation"):
        if init or repr or eq or order or unsafe_hash or frozen:
            made.append(f"{cls.__module__}.{cls.__qualname__}")
    return process(cls, init, repr, eq, order, unsafe_hash, frozen, *rest)
dataclasses._process_class = recording
from federation.cli import main
assert main(["node", "-c", "no-such-config.toml"]) == 2
print(json.dumps(sorted(made)))
"""


def test_the_node_generates_the_methods_of_few_dataclasses_at_its_start() -> None:
    # a dataclass compiles its generated methods from source as its class is made (0.2-0.7
    # ms each, agents._records): those every node imports have them written out; these
    # three are left, and a new one here is either written out or added with its reason
    done = subprocess.run(
        [sys.executable, "-c", _GENERATED],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        check=True,
    )
    assert json.loads(done.stdout.splitlines()[-1]) == [
        # federation's records: no base class to share with agents' (a private module)
        "federation._gateway.GatewayStats",
        "federation._service.GlobalResult",
        "federation._service.StreamExport",
    ]


# a zenoh node run to ready; then which transports it imported and which of our models'
# validators it built, and it stops as on SIGTERM
_ZENOH_NODE = """
import json, os, signal, sys
import federation._cli_node as node
def say(text):
    print(text, flush=True)
    if " ready in federation " in text:
        mods = [m for m in sys.modules if m.startswith(("agents.transports.", "aiomqtt", "paho"))]
        from pydantic import BaseModel
        models, built = [BaseModel], []
        while models:
            model = models.pop()
            models.extend(model.__subclasses__())
            if model.__module__.split(".")[0] in ("agents", "dyknow_core", "federation"):
                if model.__pydantic_complete__:
                    built.append(f"{model.__module__}.{model.__qualname__}")
        print(json.dumps({"imported": sorted(mods), "built": sorted(set(built))}), flush=True)
        os.kill(os.getpid(), signal.SIGTERM)
node.say = say
from federation.cli import main
sys.exit(main(["node", "-c", sys.argv[1]]))
"""


def test_a_zenoh_node_runs_without_the_other_transports_nor_rare_validators(
    tmp_path: Path,
) -> None:
    # the MQTT and in-memory transports are imported at their first use: a zenoh node
    # holds neither's code (nor the MQTT client's) for as long as it runs
    from agents.keys import gen_keys, trust_keys

    federation = f"start-{uuid.uuid4().hex[:12]}"
    public = gen_keys("n", tmp_path / "keys")[2]
    trust_keys(tmp_path / "trust.json", [public], federation=federation)
    config = tmp_path / "node.toml"
    config.write_text(
        f'name = "n"\nfederation = "{federation}"\nkey = "keys/n.key"\ntrust = "trust.json"\n'
        '[vocabulary]\nname = "start"\n[vocabulary.labels]\nspeed = "a speed"\n'
        '[mapping.labels]\nspeed = "start/speed"\n'
        '[transport]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\n'
    )
    done = subprocess.run(
        [sys.executable, "-c", _ZENOH_NODE, str(config)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "XDG_RUNTIME_DIR": str(tmp_path / "run")},
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert any(" ready in federation " in line for line in lines), done.stdout
    found = json.loads(next(line for line in lines if line.startswith("{")))
    assert found["imported"] == [
        "agents.transports._base",
        "agents.transports._mqtt_config",
        "agents.transports._zenoh",
    ]
    # validators are built for what a node validates at its start: a model of a rare
    # request (the policy of a request to share), or a table of the config validated as
    # part of PlatformConfig, builds its own when one comes; a new one here is either
    # deferred or added with its reason
    assert found["built"] == [
        "agents._df.ServiceDescription",  # its own registration
        "agents._df.ServiceQuery",
        "dyknow_core._policy.CacheSpec",  # its streams
        "dyknow_core._policy.Change",
        "dyknow_core._policy.Policy",
        "federation._platform.PlatformConfig",  # its config
    ]


def test_the_transports_imported_at_first_use_are_still_where_they_were() -> None:
    # the public surface as before: each lazily imported name resolves, in a fresh
    # interpreter (here the test run may have imported them already)
    code = (
        "import agents, agents.transports as t\n"
        "from agents import MemoryHub, MemoryTransport\n"
        "from agents.transports import MqttTransport\n"
        "from agents.transports._memory import MemoryTransport as M\n"
        "from agents.transports._mqtt import MqttTransport as Q\n"
        "assert agents.MemoryTransport is t.MemoryTransport is MemoryTransport is M\n"
        "assert agents.MemoryHub is t.MemoryHub is MemoryHub\n"
        "assert t.MqttTransport is MqttTransport is Q\n"
        "for module, name in ((agents, 'MqttTransport'), (t, 'Nothing')):\n"
        "    try:\n"
        "        getattr(module, name)\n"
        "    except AttributeError as exc:\n"
        "        print(exc)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        check=True,
    )
    assert done.stdout.splitlines() == [
        "module 'agents' has no attribute 'MqttTransport'",
        "module 'agents.transports' has no attribute 'Nothing'",
    ]
