"""The ``labkit-cli`` directive: the command-line reference, from the argparse parsers.

``.. labkit-cli::`` renders :func:`labkit.cli.build_parser`'s parser and every subcommand
under it, nested ones included (``labkit calibrate dispersion``), as sections titled with
the full command: its usage, description and arguments, with the help texts argparse
prints. The text goes into docutils nodes as it is, not through reStructuredText, so
``--help`` and the reference always say the same thing. Each section's id is the command
with dashes (``labkit-calibrate-dispersion``); ``tests/test_docs.py`` checks that every
subcommand has one.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from docutils import nodes
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective

from labkit.cli import build_parser

#: Width of the usage lines, characters.
USAGE_WIDTH = 88


def subcommands(
    parser: argparse.ArgumentParser,
) -> Iterator[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each direct subcommand of `parser`, in order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help or "" for choice in action._choices_actions}
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # aliases share a parser
                    seen.add(id(sub))
                    yield name, helps.get(name, ""), sub


def section_id(prog: str) -> str:
    """The HTML id of a command's section: ``labkit correct warp`` → ``labkit-correct-warp``."""
    return nodes.make_id(prog)


def _formatter(parser: argparse.ArgumentParser) -> argparse.HelpFormatter:
    return parser.formatter_class(prog=parser.prog, width=USAGE_WIDTH)


def _usage(parser: argparse.ArgumentParser) -> str:
    formatter = _formatter(parser)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups, prefix="")
    return formatter.format_help().strip()


def _text(text: str, *, raw: bool) -> list[nodes.Node]:
    """Paragraphs of `text` (blank-line separated), or one literal block where argparse
    prints it as written (``RawDescriptionHelpFormatter``)."""
    if raw:
        return [nodes.literal_block(text, text.strip("\n"))]
    paragraphs = [" ".join(p.split()) for p in text.split("\n\n")]
    return [nodes.paragraph(p, p) for p in paragraphs if p]


def _arguments(parser: argparse.ArgumentParser) -> list[nodes.Node]:
    """A rubric and a definition list per argument group: invocation → help."""
    formatter = _formatter(parser)
    out: list[nodes.Node] = []
    for group in parser._action_groups:
        actions = [
            a
            for a in group._group_actions
            if a.help is not argparse.SUPPRESS and not isinstance(a, argparse._SubParsersAction)
        ]
        if not actions:
            continue
        out.append(nodes.rubric(group.title or "", group.title or ""))
        if group.description:
            out.extend(_text(group.description, raw=False))
        items = nodes.definition_list()
        for action in actions:
            invocation = formatter._format_action_invocation(action)
            term = nodes.term("", "", nodes.literal(invocation, invocation))
            help_text = formatter._expand_help(action) if action.help else ""
            definition = nodes.definition("", *_text(help_text, raw=False))
            items += nodes.definition_list_item("", term, definition)
        out.append(items)
    return out


class CommandLineReference(SphinxDirective):
    """``.. labkit-cli::`` — a section per command of ``labkit``, nested as the commands are."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        return [self._section(build_parser(), "")]

    def _section(self, parser: argparse.ArgumentParser, summary: str) -> nodes.section:
        prog = parser.prog
        section = nodes.section(ids=[section_id(prog)], names=[nodes.fully_normalize_name(prog)])
        self.state.document.note_implicit_target(section, section)
        section += nodes.title(prog, "", nodes.literal(prog, prog))
        if summary:
            section += nodes.paragraph(summary, summary, classes=["lead"])
        usage = _usage(parser)
        section += nodes.literal_block(usage, usage, language="none")
        raw = issubclass(parser.formatter_class, argparse.RawDescriptionHelpFormatter)
        if parser.description:
            section.extend(_text(parser.description, raw=raw))
        section.extend(_arguments(parser))
        children = list(subcommands(parser))
        if children:
            section += nodes.rubric("subcommands", "subcommands")
            items = nodes.bullet_list()
            for name, help_text, sub in children:
                link = nodes.reference(
                    sub.prog, "", nodes.literal(name, name), refid=section_id(sub.prog)
                )
                para = nodes.paragraph("", "", link)
                if help_text:
                    para += nodes.Text(f": {help_text}")
                items += nodes.list_item("", para)
            section += items
        if parser.epilog:
            section.extend(_text(parser.epilog, raw=raw))
        for _, help_text, sub in children:
            section += self._section(sub, help_text)
        return section


def setup(app: Sphinx) -> dict[str, object]:
    app.add_directive("labkit-cli", CommandLineReference)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
