"""``kc-train METHOD --data SCENE``: train a registered method (the trainer arrives with the model issue)."""

from __future__ import annotations

import sys

from kc_splatfacto.registry import discover_methods


def entrypoint(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    methods = discover_methods()
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: kc-train METHOD --data SCENE [options]\n\nmethods:")
        for name, spec in methods.items():
            print(f"  {name:<28} {spec.description}")
        if not methods:
            print("  (none registered)")
        return 0
    print(f"kc-train: training is not wired up yet; registered methods: {', '.join(methods) or 'none'}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(entrypoint())
