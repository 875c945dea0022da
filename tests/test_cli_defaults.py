"""The CLI reads its defaults from the settings dataclasses: a command line that gives no option builds the
same settings as the dataclass's own defaults."""

from __future__ import annotations

from dataclasses import asdict, fields

from favormap.build_config import BuildConfig
from favormap.cli import build as cli_build
from favormap.cli import localize as cli_localize
from favormap.cli import make_parser
from favormap.localize import LocalizeConfig


def test_build_options_left_out_give_the_build_config_defaults():
    args = make_parser().parse_args(["build", "seq", "-o", "map.h5"])
    assert cli_build.config_from_args(args).to_dict() == BuildConfig().to_dict()


def test_build_options_left_out_give_the_defaults_of_another_extractor_too():
    args = make_parser().parse_args(["build", "seq", "-o", "map.h5", "--extractor", "disk"])
    assert cli_build.config_from_args(args).to_dict() == BuildConfig(extractor="disk").to_dict()


def test_localize_options_left_out_give_the_localize_config_defaults():
    args = make_parser().parse_args(["localize", "map.h5", "query.png", "--device", "cpu"])
    got, want = asdict(cli_localize.config_from_args(args)), asdict(LocalizeConfig())
    assert got.pop("threads") == "auto"  # the CLI sizes the pools; the library leaves them alone
    want.pop("threads")
    assert got == want
    assert {f.name for f in fields(LocalizeConfig)} - set(got) == {"threads"}


def test_align_merge_and_query_options_left_out_give_their_settings_defaults():
    from favormap.cli import align as cli_align
    from favormap.cli import merge as cli_merge
    from favormap.cli import query as cli_query
    from favormap.ops.align_config import AlignConfig
    from favormap.ops.merge_config import MergeConfig
    from favormap.view_limits import ViewLimits

    parser = make_parser()
    assert cli_align.align_config(parser.parse_args(["align", "a.h5", "b.h5"])) == AlignConfig()
    merge_args = parser.parse_args(["merge", "a.h5", "b.h5", "-o", "m.h5"])
    assert cli_merge.merge_config(merge_args) == MergeConfig()
    assert cli_align.align_config(merge_args) == AlignConfig()
    query_args = parser.parse_args(["query", "map.h5", "--pose", "pose.txt"])
    assert cli_query.view_limits(query_args) == ViewLimits()
