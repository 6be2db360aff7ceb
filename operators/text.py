"""How VP-FFD words what it shows: sentences, one number format, lines that fit the panel."""
import textwrap

PREFIX = "VP-FFD: "      #: every operator report starts with it (console and farm logs search it)


def sentence(text):
    """`text` as a sentence: capital first letter, final full stop (kept: ! ? and a closing
    parenthesis after a stop)."""
    text = " ".join(str(text).split())
    if not text:
        return text
    text = text[0].upper() + text[1:]
    return text if text.endswith((".", "!", "?", ".)")) else text + "."


def count(n):
    """An integer count as the panel writes every number of things: 2,562."""
    return f"{int(n):,}"


def percent(x):
    """A percentage as the panel writes every one of them, to the README's volume bound
    (1e-5 of the volume is 0.001%): 100.000%."""
    return f"{float(x):.3f}%"


def lines(text, width):
    """`text` cut into lines of at most `width` characters (at least 20), at spaces."""
    return textwrap.wrap(text, max(20, int(width)), break_long_words=False) or [""]


def report(operator, level, text):
    """`operator.report` with the VP-FFD prefix and the text as a sentence."""
    operator.report({level}, PREFIX + sentence(text))
