"""How the ``gtforge`` command's help looks: ``SESSION``/``PATH`` placeholders instead of typer's ``{session}``,
``<path>`` or ``<bool>``, for every command present and future (click parameters, duck-typed: typer may vendor its own
click)."""
from __future__ import annotations

import re
import shutil
from contextlib import contextmanager

from rich.markup import escape
from typer.core import TyperArgument, TyperCommand, TyperGroup

# the commands in the order a lab runs them (help lists them so); any other command follows, in definition order
WORKFLOW = ("run", "calibrate", "align-depth", "validate", "calibrate-scale", "refine", "build-dataset", "verify",
            "evaluate", "compare", "synth", "demo")


# the group's flags a command line may also give after the command's name (``_Group.parse_args``)
GROUP_FLAGS = ("-v", "--verbose")


def _unwrapped(text: str | None) -> str | None:
    """A docstring's paragraphs as single lines: the help wraps them to the terminal, never at the source's line
    ends (which made a help line break mid-sentence)."""
    if not text:
        return text
    return "\n\n".join(re.sub(r"\s*\n\s*", " ", p.strip()) for p in re.split(r"\n\s*\n", text.strip()))


def _plain_metavars(params: list) -> None:
    """Help and usage show ``SESSION``/``PATH``, never typer's ``{session}``/``<path>``/``<bool>``/``<list[Path]>``:
    arguments get their upper-case name, flags no value placeholder, other options their type's name
    (click parameters, duck-typed: typer may vendor its own click)."""
    for p in params:
        if p.metavar is not None:
            continue
        if p.param_type_name == "argument":
            p.metavar = (p.name or "").upper()
            if type(p) is TyperArgument:
                p.__class__ = _Argument
        elif p.param_type_name == "option":
            p.metavar = "" if getattr(p, "is_flag", False) else _type_name(p)



def _type_name(p) -> str:
    """``TEXT``/``INTEGER``/``FLOAT``/``PATH`` for an option without a metavar."""
    t = getattr(p, "type", None)  # click's parameter type (typer < 0.20 and click itself)
    name = getattr(t, "name", None) if t is not None else None
    if name is None and hasattr(p, "display_type"):  # newer typer: "<int>", "<path>", ...
        name = str(p.display_type(None) or "value").strip("<>")
    name = str(name or "value").upper()
    return {"STR": "TEXT", "INT": "INTEGER"}.get(name, name)



class _Argument(TyperArgument):
    def display_type_rich(self, ctx):  # the name column already shows the metavar; no "<path>"/"<list[Path]>"
        return None



def _rich_table_width(cmd, ctx) -> int:
    """About the width typer's option table needs to show every option's names, placeholder and one help word whole
    (it cuts a cell that does not fit to "…", names included): its columns side by side, plus borders and gaps."""
    names = secondary = metavar = 0
    word = 20
    for p in cmd.get_params(ctx):
        opts = [o for o in p.opts if o.startswith("--")] or p.opts
        names = max(names, len(", ".join(opts)))
        secondary = max(secondary, len(", ".join(p.secondary_opts + [o for o in p.opts if o not in opts])))
        metavar = max(metavar, len(p.make_metavar(ctx) if p.metavar is None else p.metavar) + 12)
        word = max([word] + [len(w) for w in (getattr(p, "help", None) or "").split()])
    return 4 + names + 2 + secondary + 2 + metavar + 2 + word + 8  # (+6: rich's own padding, measured)


def _escape_markup(obj) -> None:
    """typer's boxed help reads every help text as rich markup, which dropped a bracketed word ("calibrate ->
    [align-depth] ->" showed as "calibrate ->  ->"): the texts are escaped once, their plain words kept beside them
    (``_plain_help``) for click's plain help."""
    for o in (obj, *getattr(obj, "params", ())):
        text = getattr(o, "help", None)
        if text and not hasattr(o, "_plain_help"):
            o._plain_help = text
            o.help = escape(text)


@contextmanager
def _plain_texts(cmd):
    """The command's help texts as written (not escaped for rich) while click's plain help formats them."""
    objs = [o for o in (cmd, *cmd.params) if hasattr(o, "_plain_help")]
    escaped = [o.help for o in objs]
    for o in objs:
        o.help = o._plain_help
    try:
        yield
    finally:
        for o, text in zip(objs, escaped):
            o.help = text


class _Command(TyperCommand):
    def format_help(self, ctx, formatter):
        """typer's boxed help where the terminal is wide enough for it; else click's plain help, which wraps
        instead of cutting option names short (``--legacy-patte…`` at 80 columns)."""
        if shutil.get_terminal_size().columns < _rich_table_width(self, ctx):
            with _plain_texts(self):
                return super(TyperCommand, self).format_help(ctx, formatter)
        return super().format_help(ctx, formatter)

    def collect_usage_pieces(self, ctx) -> list[str]:
        return [piece.replace("{", "").replace("}", "") for piece in super().collect_usage_pieces(ctx)]

    def get_help_option(self, ctx):
        opt = super().get_help_option(ctx)
        if opt is not None:
            _plain_metavars([opt])
        return opt



class _Group(TyperGroup):
    """Applies ``_plain_metavars`` to every command (present and future) and to the group's own options."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _plain_metavars(self.params)
        _escape_markup(self)
        for cmd in self.commands.values():
            if type(cmd) is TyperCommand:
                cmd.__class__ = _Command
            _plain_metavars(cmd.params)
            cmd.help = _unwrapped(cmd.help)
            _escape_markup(cmd)

    def parse_args(self, ctx, args: list[str]) -> list[str]:
        """The group's ``-v``/``--verbose`` is taken after the command too (``gtforge build-dataset S -v``, as users
        type it): moved before the command's name, up to a ``--``. No command has a ``-v`` of its own
        (``tests/cli/test_cli.py`` checks)."""
        first = next((i for i, a in enumerate(args) if a in self.commands), None)
        if first is not None:
            end = first + args[first:].index("--") if "--" in args[first:] else len(args)
            flags = [a for a in args[first + 1:end] if a in GROUP_FLAGS]
            if flags:
                args = args[:first] + flags + [a for i, a in enumerate(args)
                                               if i >= first and not (first < i < end and a in GROUP_FLAGS)]
        return super().parse_args(ctx, args)

    def list_commands(self, ctx) -> list[str]:
        names = list(self.commands)
        return [n for n in WORKFLOW if n in self.commands] + [n for n in names if n not in WORKFLOW]

    def get_help_option(self, ctx):
        opt = super().get_help_option(ctx)
        if opt is not None:
            _plain_metavars([opt])
        return opt
