"""The sandbox a Cartographer Lua configuration runs in (``options.cartographer_lua`` reads what it sets).

A configuration is shared like a recording (copied from a forum), so running one may compute option values and
nothing else: no files, processes, Python, or bytecode, and no unbounded work (SECURITY.md).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from carto_cli.core.errors import CartoError

__all__ = ["Sandbox", "source"]

# Every chunk (the prelude, the stock files, the user's files) is loaded as text into one environment built from an
# allow-list; the real globals, which hold the loaders and lupa's `python` module, stay with the host closures below
# and are never reachable.

# Safety bounds, not tuning knobs: a configuration runs some 10^4 Lua instructions and needs well under a MB.
INSTRUCTION_LIMIT = 50_000_000  # some 0.3 s of a tight loop: thousands of times what a configuration needs
TIME_LIMIT = 5.0  # seconds; for instructions that are each slow (copying strings of many MB)
HOOK_INTERVAL = 1_000  # instructions between checks: Ctrl-C is seen within microseconds, at a few % of speed
MEMORY_LIMIT = 64 << 20  # bytes the Lua state may hold
WORK_LIMIT = 10**8  # the estimated steps a single library call (a pattern match) may take: it cannot be hooked
MAX_SOURCE_BYTES = 1 << 20  # a configuration file is a few KB; this keeps an include of a huge file out of memory
_FORBIDDEN = ("os, io, package, require, dofile, loadfile, load, debug",
              "loadstring collectgarbage python coroutine setfenv getfenv module newproxy jit ffi")

# Run in the full runtime once, before any configuration: what carto itself needs (load, the debug hook) stays in
# locals of these closures. Library calls run in C, where the instruction hook cannot stop them, so the few whose
# work a configuration could make unbounded are replaced: pattern matching is refused beyond WORK_LIMIT, and
# table.insert/remove/move (whose loops follow a __len the configuration defines) are written in Lua, where every
# step is counted. A finalizer (__gc) runs with hooks off, so it is refused; so would xpcall's handler when the
# hook raised the error, so it is called after. pcall and xpcall re-raise once the configuration has been stopped,
# so catching the stop does not outlive it.
_SANDBOX = """
local include_file, tick, write, limits, forbidden, why_forbidden = ...
local load, pcall, xpcall, error, select, type, tostring, rawget, setmetatable, getmetatable, pairs =
  load, pcall, xpcall, error, select, type, tostring, rawget, setmetatable, getmetatable, pairs
local sethook, getinfo, gsub, gmatch, format, concat, pack, unpack, utf8len = debug.sethook, debug.getinfo,
  string.gsub, string.gmatch, string.format, table.concat, table.pack, table.unpack, utf8.len
local state = {}

-- carto's own refusal, `level` as error's (from fail's caller); Python reports it without "Lua error:"
local function fail(message, level) state.own = message; error(message, level + 1) end
local function stop(message)  -- for good: pcall re-raises it
  state.own, state.stop = message, (state.src or "?") .. ":" .. (state.line or 0) .. ": " .. message
  error(state.stop, 0)
end
local function host(f, ...)  -- a Python call: its exception (Ctrl-C, or a bug) ends the run, and Python raises it
  local ok, a, b = pcall(f, ...)
  if not ok then state.failure = a; state.src, state.line = "?", 0; stop("stopped") end
  return a, b
end
sethook(function()
  if state.stop then error(state.stop, 0) end
  local level, info = 2, getinfo(2, "Sl")  -- the configuration's line running now, not carto's code it called
  while info and (info.source == "=carto" or info.currentline < 0) do level = level + 1; info = getinfo(level, "Sl") end
  if info then state.src, state.line = info.short_src, info.currentline end
  local why = host(tick)
  if why then stop(why) end
end, "", limits.hook)
local function copy(t) local c = {} for k, v in pairs(t) do c[k] = v end return c end
local function refuse(names, prefix)  -- a metatable: a clear error for names taken away, nil for others
  local set = {}
  for name in gmatch(names, "[%w_]+") do set[name] = true end
  return {__metatable = false, __index = function(_, name)
    if set[name] then
      fail(format("'%s%s' is not available to a configuration (%s)", prefix, name, why_forbidden), 2)
    end
  end}
end

local env = {_VERSION = _VERSION}
for name in gmatch("pairs ipairs next type tostring tonumber select error assert getmetatable rawget rawset " ..
                   "rawequal rawlen", "%S+") do env[name] = _G[name] end
env.math, env._G = copy(math), env
local function checked(ok, ...) if state.stop then error(state.stop, 0) end return ok, ... end
env.pcall = function(...) return checked(pcall(...)) end
-- The handler is called after the error, not within it: within an error the hook raised, hooks are off.
env.xpcall = function(f, handler, ...)
  local result = pack(pcall(f, ...))
  checked()
  if result[1] then return unpack(result, 1, result.n) end
  return false, (handler(result[2]))
end
env.setmetatable = function(t, mt)
  if type(mt) == "table" and rawget(mt, "__gc") ~= nil then
    fail("'__gc' is not available to a configuration (a finalizer would run outside carto's limits)", 2)
  end
  return setmetatable(t, mt)
end
env.print = function(...)
  local parts = {}
  for i = 1, select("#", ...) do parts[i] = tostring((select(i, ...))) end
  local line = concat(parts, "\\t")
  host(write, utf8len(line) and line or gsub(line, "[\\128-\\255]", "?"))
end

local str = copy(string)
str.dump = nil  -- bytecode: nothing may load it, and nothing is to be made of it
local function bounded(name)
  local f = string[name]
  str[name] = function(s, p, ...)
    local ts, tp = type(s), type(p)
    if (ts == "string" or ts == "number") and (tp == "string" or tp == "number") then
      local subject, pattern = tostring(s), tostring(p)
      -- Backtracking tries up to #s lengths per quantifier (and per back reference or %b), from #s+1 starts.
      local loops = select(2, gsub(pattern, "[%*%+%-]", "")) + select(2, gsub(pattern, "%%[b1-9]", ""))
      local cost = (#subject + 1) ^ (loops + 1) * 2 ^ select(2, gsub(pattern, "%?", "")) * (#pattern + 1)
      if cost > limits.work then
        fail(format("string.%s: this pattern on %d characters may take too long (carto bounds a configuration's work)",
                    name, #subject), 2)
      end
    end
    return f(s, p, ...)
  end
end
for _, name in ipairs({"find", "match", "gmatch", "gsub"}) do bounded(name) end
env.string = setmetatable(str, refuse("dump", "string."))
local strings = getmetatable("")
strings.__index, strings.__metatable = str, false

local tbl = copy(table)
function tbl.insert(t, ...)
  local e, n = #t + 1, select("#", ...)
  if n == 1 then t[e] = ...; return end
  local pos, value = ...
  if n ~= 2 then error("wrong number of arguments to 'insert'", 2) end
  if type(pos) ~= "number" or pos < 1 or pos > e then
    error("bad argument #2 to 'insert' (position out of bounds)", 2)
  end
  for i = e, pos + 1, -1 do t[i] = t[i - 1] end
  t[pos] = value
end
function tbl.remove(t, pos)
  local size = #t
  if pos == nil then pos = size end
  if pos ~= size and (type(pos) ~= "number" or pos < 1 or pos > size + 1) then
    error("bad argument #2 to 'remove' (position out of bounds)", 2)
  end
  local value = t[pos]
  for i = pos, size - 1 do t[i] = t[i + 1] end
  t[pos < size and size or pos] = nil
  return value
end
function tbl.move(a1, f, e, t, a2)
  if a2 == nil then a2 = a1 end
  if e >= f then
    if t > e or t <= f or a1 ~= a2 then for i = 0, e - f do a2[t + i] = a1[f + i] end
    else for i = e - f, 0, -1 do a2[t + i] = a1[f + i] end end
  end
  return a2
end
env.table, env.unpack = tbl, unpack

local function run(code, label)
  local chunk, err = load(code, "@" .. label, "t", env)
  if not chunk then error(err, 0) end
  return chunk()
end
env.include = function(name)
  name = tostring(name)
  if not utf8len(name) then fail("include: the name is not UTF-8 text", 2) end
  local code, label = host(include_file, name)
  if code then run(code, label) elseif label then fail(label, 2) end
end
setmetatable(env, refuse(forbidden, ""))
return env, state, run
"""


def _no_attributes(obj: Any, name: Any, is_setting: bool) -> Any:
    """lupa's attribute filter: no Python object's attributes (``__globals__``, ``__class__``...) from Lua."""
    raise AttributeError("Python attributes are not available to a configuration")


def source(path: Path) -> str:
    """The text of a configuration file; CartoError (naming ``path``) when it is not one."""
    try:
        with path.open("rb") as f:
            data = f.read(MAX_SOURCE_BYTES + 1)
    except OSError as e:
        raise CartoError(f"cannot read it: {e.strerror}", path) from None
    if data.startswith(b"\x1b"):  # what Lua takes for a precompiled chunk
        raise CartoError("line 1: a precompiled (binary) Lua chunk: carto runs configurations from their source "
                         "text only", path)
    if len(data) > MAX_SOURCE_BYTES:
        raise CartoError(f"larger than {MAX_SOURCE_BYTES >> 10} KiB: not a configuration", path)
    return data.decode(errors="replace")


class Sandbox:
    """One configuration's Lua runtime: :data:`_SANDBOX`'s environment, the includes it resolves, and its errors
    as one CartoError naming the file and line."""

    def __init__(self, path: Path, stock: dict[str, str]):
        from lupa import LuaRuntime

        self.path, self.stock = path, stock
        self.files: dict[str, Path | None] = {}  # chunk name (as Lua shows it) -> its file (None: a stock file)
        self.included: set[str] = set()
        self.ticks = 0
        self.deadline = time.monotonic() + TIME_LIMIT
        lua = LuaRuntime(unpack_returned_tuples=True, register_eval=False, register_builtins=False,
                         attribute_filter=_no_attributes, max_memory=MEMORY_LIMIT)
        limits = lua.table_from({"hook": HOOK_INTERVAL, "work": WORK_LIMIT})
        self.env, self.state, self._run = lua.execute(_SANDBOX, self.include, self.tick, _print, limits,
                                                      " ".join(_FORBIDDEN), "carto runs configurations without "
                                                      + _FORBIDDEN[0], name="=carto", mode="t")

    def run(self, code: str, path: Path | None, name: str) -> Any:
        """Run one chunk (the prelude with ``path`` None); a configuration's error as a CartoError."""
        from lupa import LuaError

        try:
            return self._run(code, self._label(name, path))
        except LuaError as e:
            raise self._error(e) from None
        except UnicodeDecodeError as e:  # what it returns: Python takes Lua's strings as UTF-8
            raise CartoError(f"it returns a string that is not UTF-8 text ({e.reason})", path or self.path) from None

    def include(self, name: str) -> tuple[str | None, str | None]:
        """(code, chunk name) of ``include name``, (None, None) when already included, (None, why) if it cannot."""
        if name in self.included:
            return None, None
        self.included.add(name)
        candidate = self.path.parent / name
        try:
            found = candidate.is_file() and candidate.resolve() != self.path.resolve()
        except (OSError, ValueError):  # a name no file can have
            found = False
        if found:
            try:
                return source(candidate), self._label(name, candidate)
            except CartoError as e:
                return None, f'include "{name}": {e.message}'
        if name in self.stock:
            return self.stock[name], self._label(name, None)
        return None, (f'include "{name}": not found next to {self.path.name}, and not one of Cartographer\'s stock '
                      f"files ({', '.join(sorted(self.stock))})")

    def tick(self) -> str | None:
        """Every HOOK_INTERVAL instructions: why to stop, if so (and, being Python, a pending Ctrl-C is raised)."""
        self.ticks += 1
        if self.ticks * HOOK_INTERVAL > INSTRUCTION_LIMIT:
            return (f"still running after {INSTRUCTION_LIMIT:,} Lua instructions: carto stops a configuration "
                    "there (it only computes option values; an endless loop?)")
        if time.monotonic() > self.deadline:
            return f"still running after {TIME_LIMIT:g} s: carto stops a configuration there"
        return None

    def _label(self, name: str, path: Path | None) -> str:
        # Lua shows a chunk name of up to 59 characters as it is: then an error's "name:line:" finds the file.
        label = name if len(name) <= 59 else "..." + name[-56:]
        if label in self.files and self.files[label] != path:
            label = (f"carto's {name}" if path is None else f"#{len(self.files)} {name}")[:59]
        self.files[label] = path
        return label

    def _error(self, error: Exception) -> BaseException:
        from lupa import LuaMemoryError

        if isinstance(self.state.failure, BaseException):  # Ctrl-C (or a bug) in a Python call: as it was
            return self.state.failure
        lines = str(error).strip().splitlines()
        text, label, line = (lines[0] if lines else ""), None, None
        if isinstance(error, LuaMemoryError) or text == "not enough memory":
            text = f"ran out of memory (carto lets a configuration use {MEMORY_LIMIT >> 20} MB)"
            label, line = self.state.src, self.state.line  # where it last was: a memory error has no position
        for known in sorted(self.files, key=len, reverse=True):  # "name:line: message", name as Lua shows it
            number, _, rest = text[len(known) + 1:].partition(": ")
            if text.startswith(known + ":") and number.isdigit():
                label, line, text = known, int(number), rest
                break
        own = text == self.state.own or text.startswith("ran out of memory")
        text = text if own else f"Lua error: {text or 'an error value that is not a string'}"
        if label not in self.files or line is None:
            return CartoError(text, self.path)
        path = self.files[label]
        if path is None:
            return CartoError(f"line {line} of carto's stock {label}: {text}", self.path)
        return CartoError(f"line {line}: {text}" + ("" if path == self.path else f" (included by {self.path.name})"),
                          path)


def _print(line: str) -> None:
    """A configuration's print: to stderr, where carto's output (a profile on stdout) stays clean."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()
