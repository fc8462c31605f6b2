"""A `jq` for the documented examples where the jq program is not installed (the `jq` wheel: libjq itself).

Usage as jq's: ``jq [-c] [-r] FILTER [FILE ...]``; the inputs are a stream of JSON values (JSON Lines).
Output as jq's: one value a line with -c, else indented by two spaces; -r prints strings raw.
"""
import json
import sys


def main(argv):
    import jq

    flags = [a for a in argv if a.startswith("-") and len(a) > 1]
    rest = [a for a in argv if not (a.startswith("-") and len(a) > 1)]
    unknown = set("".join(f.lstrip("-") for f in flags)) - set("cr")
    if unknown or not rest:
        sys.stderr.write(f"jq shim: unsupported options {sorted(unknown)} or no filter\n")
        return 2
    program, files = rest[0], rest[1:]
    text = "".join(open(f, encoding="utf-8").read() for f in files) if files else sys.stdin.read()
    for value in jq.compile(program).input_text(text).all():
        if "r" in "".join(flags) and isinstance(value, str):
            print(value)
        else:
            print(json.dumps(value, separators=(",", ":")) if "c" in "".join(flags) else json.dumps(value, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
