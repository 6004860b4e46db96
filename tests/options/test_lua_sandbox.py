"""carto_cli.options.lua_sandbox: a configuration computes option values, and nothing else (SECURITY.md).

Each case is run through import_lua, as every command that reads a configuration runs it."""
import resource
import signal
import subprocess
import sys
import threading
import time

import pytest
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core.errors import CartoError
from carto_cli.options.cartographer_lua import import_lua


def write(tmp_path, text, name="robot.lua"):
    p = tmp_path / name
    p.write_text(text)
    return p


# Each escape is a configuration's line 2 (line 1 includes a stock file, as configurations do) that, run with the
# full Lua and lupa's bridge to Python, creates {canary}; {helper} is a file of Lua that does.
ESCAPES = {
    "os.execute": 'os.execute("touch {canary}")',
    "io.open": 'io.open("{canary}", "w"):close()',
    "io.popen": 'io.popen("touch {canary}"):close()',
    "require": 'require("os").execute("touch {canary}")',
    "package.loadlib": 'assert(package.loadlib) package.loaded.os.execute("touch {canary}")',
    "dofile": 'dofile("{helper}")',
    "loadfile": 'loadfile("{helper}")()',
    "load": 'load("os.execute([[touch {canary}]])")()',
    "loadstring": 'local compile = loadstring or load compile("os.execute([[touch {canary}]])")()',
    "string.dump": 'local f = string.dump(function() os.execute("touch {canary}") end) load(f, "f", "b")()',
    "debug": 'debug.getregistry()._LOADED.os.execute("touch {canary}")',
    "python.eval": """python.eval("__import__('os').system('touch {canary}')")""",
    "python.builtins": 'python.builtins.__import__("os").system("touch {canary}")',
    "python.none": ('local a = python.as_attrgetter for c in python.iter(a(a(a(python.none).__class__).__base__)'
                    '.__subclasses__()) do if a(c).__name__ == "_wrap_close" then '
                    'a(a(c).__init__).__globals__.system("touch {canary}") end end'),
    "include.__globals__": 'include.__globals__.__builtins__.__import__("os").system("touch {canary}")',
}


def refused(path):
    """import_lua's CartoError for ``path`` (None if it imports)."""
    try:
        import_lua(path)
    except CartoError as e:
        return e
    return None


@pytest.mark.parametrize("route", sorted(ESCAPES))
def test_a_configuration_reaches_nothing_beyond_its_options(tmp_path, route):
    canary = tmp_path / "PWNED"
    helper = write(tmp_path, f'os.execute("touch {canary}")\n', "helper.lua")
    cfg = write(tmp_path, 'include "map_builder.lua"\n' + ESCAPES[route].format(canary=canary, helper=helper) + "\n")
    error = refused(cfg)
    assert not canary.exists()
    assert error is not None and str(error).startswith(f"{cfg}: line 2: "), error


def test_a_forbidden_name_in_an_included_file_names_that_file(tmp_path):
    helper = write(tmp_path, 'local x = 1\nio.write("x")\n', "sensors.lua")
    cfg = write(tmp_path, 'include "sensors.lua"\ninclude "pose_graph.lua"\n')
    assert str(refused(cfg)) == (f"{helper}: line 2: 'io' is not available to a configuration (carto runs "
                                 "configurations without os, io, package, require, dofile, loadfile, load, debug) "
                                 "(included by robot.lua)")


def precompiled(canary):
    """A chunk of Lua bytecode that creates ``canary``, from a runtime of its own with the whole of Lua."""
    from lupa import LuaRuntime

    return LuaRuntime(encoding=None).eval(f'string.dump(function() os.execute("touch {canary}") end)')


def test_a_precompiled_chunk_is_refused(tmp_path):
    canary = tmp_path / "PWNED"
    direct = tmp_path / "robot.luac"
    direct.write_bytes(precompiled(canary))
    (tmp_path / "evil.luac").write_bytes(precompiled(canary))
    included = write(tmp_path, 'include "map_builder.lua"\ninclude "evil.luac"\n')
    for cfg, line in ((direct, 1), (included, 2)):
        error = refused(cfg)
        assert not canary.exists()
        assert error is not None and str(error).startswith(f"{cfg}: line {line}: "), error
        assert "precompiled" in str(error)


# Line 2 of a configuration that would run for ever, or fill memory, without carto's bounds -> what stops it.
RUNAWAY = {
    "an endless loop": ("while true do end", "still running after"),
    "a loop that catches its stop": ("while true do pcall(function() while true do end end) end", "still running"),
    "a message handler that loops": ("xpcall(function() while true do end end, function() while true do end end)",
                                     "still running"),
    "a finalizer that loops": ("setmetatable({}, {__gc = function() while true do end end}) "
                               "for i = 1, 1e7 do local t = {} end", "'__gc' is not available"),
    "a backtracking pattern": ('string.find(("a"):rep(40), ("a*"):rep(20) .. "b")', "pattern"),
    "a length that lies": ("table.insert(setmetatable({}, {__len = function() return 1e12 end}), 1, 0)",
                           "still running"),
    "a memory bomb": ('local t = {} while true do t[#t + 1] = ("x"):rep(1000) .. #t end', "ran out of memory"),
}
IMPORT = """
import sys
from carto_cli.core.errors import CartoError
from carto_cli.options.cartographer_lua import import_lua
try:
    import_lua(sys.argv[1])
except CartoError as e:
    print(e)
"""


def bounded_data():
    resource.setrlimit(resource.RLIMIT_DATA, (1 << 30, 1 << 30))


@pytest.mark.parametrize("case", sorted(RUNAWAY))
def test_a_configuration_cannot_run_away(tmp_path, case):
    # In a process of its own, with its memory bounded: what is tested here would otherwise hang the tests or
    # fill the machine's memory if the bounds failed.
    code, message = RUNAWAY[case]
    cfg = write(tmp_path, f'include "map_builder.lua"\n{code}\n')
    started = time.monotonic()
    r = subprocess.run([sys.executable, "-c", IMPORT, str(cfg)], capture_output=True, text=True, timeout=60,
                       preexec_fn=bounded_data)
    assert r.returncode == 0 and r.stdout.startswith(f"{cfg}: line 2: "), (r.stdout, r.stderr[-2000:])
    assert message in r.stdout and time.monotonic() - started < 30


INTERRUPTED = """
import carto_cli.options.lua_sandbox as lua
lua.INSTRUCTION_LIMIT = lua.TIME_LIMIT = 10**12  # so that only Ctrl-C ends it
from carto_cli.cli import main
main()
"""


def test_ctrl_c_interrupts_a_configuration_that_runs(tmp_path):
    cfg = write(tmp_path, 'include "map_builder.lua"\nprint("looping")\nwhile true do end\n')
    # A shell without job control starts background jobs with SIGINT ignored; a user at a terminal has the default.
    p = subprocess.Popen([sys.executable, "-c", INTERRUPTED, "options", "import", str(cfg)], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    watchdog = threading.Timer(60, p.kill)
    watchdog.start()
    try:
        assert p.stdout.readline() == "looping\n"  # the configuration is running: the loop is next
        time.sleep(0.2)
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=30)
    finally:
        watchdog.cancel()
        p.kill()
    assert p.returncode == 130 and out.strip() == "carto: interrupted", (p.returncode, out[-2000:])


def test_the_command_line_refuses_a_configuration_in_one_line(tmp_path):
    canary = tmp_path / "PWNED"
    cfg = write(tmp_path, f'include "map_builder.lua"\nos.execute("touch {canary}")\nreturn {{}}\n')
    r = CliRunner().invoke(app, ["options", "import", str(cfg)])
    assert not canary.exists()
    assert r.exit_code == 2, r.output
    (line,) = r.stderr.strip().splitlines()
    assert line == (f"carto: error: {cfg}: line 2: 'os' is not available to a configuration (carto runs "
                    "configurations without os, io, package, require, dofile, loadfile, load, debug)")


def test_print_writes_to_stderr(tmp_path):
    """stdout holds the imported profile."""
    cfg = write(tmp_path, 'include "trajectory_builder_2d.lua"\nprint("min range", 0.5)\n'
                "TRAJECTORY_BUILDER_2D.min_range = 0.5\n")
    r = CliRunner().invoke(app, ["options", "import", str(cfg)])
    assert r.exit_code == 0, r.output
    assert "min range\t0.5" in r.stderr and "min range" not in r.stdout and "min_range: 0.5" in r.stdout


def test_what_the_sandbox_leaves_works_as_in_lua(tmp_path):
    """The library a configuration keeps (some of it rewritten so that its work is bounded) behaves as Lua's."""
    cfg = write(tmp_path, """include "trajectory_builder_2d.lua"
local t = {3, 1, 2}
table.insert(t, 4) table.insert(t, 1, 0) table.sort(t)
assert(table.concat(t, ",") == "0,1,2,3,4")
assert(table.remove(t, 1) == 0 and table.remove(t) == 4 and table.concat(t, ",") == "1,2,3")
assert(table.remove({}) == nil and table.concat(table.move({1, 2, 3}, 1, 3, 2), ",") == "1,1,2,3")
assert(("a.b.c"):gsub("%.", "_") == "a_b_c" and string.format("%.1f", math.rad(180)) == "3.1")
assert(string.match("range=8.5", "(%a+)=([%d.]+)") == "range" and select("#", string.find("abc", "b")) == 2)
assert(select(2, pcall(error, "x", 0)) == "x" and table.unpack({1, 2}) == 1 and undefined_global == nil)
assert(select(2, xpcall(error, function(e) return "handled " .. e end, "x", 0)) == "handled x")
assert(select("#", xpcall(function() return 1, 2 end, print)) == 3)
TRAJECTORY_BUILDER_2D.min_range = tonumber(("%g"):format(0.25))
""")
    assert import_lua(cfg).overrides == {"trajectory_builder_2d.min_range": 0.25}
