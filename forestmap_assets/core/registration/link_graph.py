"""The graph of scan links, for the pairs to search (inferred, issue 16): a link that lies on no
loop (a *bridge*) cannot be checked by the residuals of the optimal map (spec 7.3: a wrong link
shows only as a loop's misclosure), so the screened pairs close loops over their bridges and a
bridge left by a failed pair is retried (:mod:`.screening`, :mod:`.candidates`)."""

from __future__ import annotations

from collections.abc import Iterable


def _adjacency(edges: Iterable[tuple[str, str]]) -> dict[str, list[tuple[str, int]]]:
    adj: dict[str, list[tuple[str, int]]] = {}
    for k, (a, b) in enumerate(edges):
        adj.setdefault(a, []).append((b, k))
        adj.setdefault(b, []).append((a, k))
    return adj


def bridges(edges: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The edges of ``edges`` (undirected, no repeats) that lie on no cycle, in ``edges`` order
    (Tarjan's low-link test, iterative)."""
    adj = _adjacency(edges)
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    found: set[int] = set()
    for start in adj:
        if start in order:
            continue
        order[start] = low[start] = len(order)
        stack = [(start, -1, iter(adj[start]))]
        while stack:
            node, via, it = stack[-1]
            step = next(it, None)
            if step is None:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[node])
                    if low[node] > order[parent]:
                        found.add(via)
                continue
            nxt, k = step
            if k == via:
                continue
            if nxt in order:
                low[node] = min(low[node], order[nxt])
            else:
                order[nxt] = low[nxt] = len(order)
                stack.append((nxt, k, iter(adj[nxt])))
    return [e for k, e in enumerate(edges) if k in found]


def sides(edges: list[tuple[str, str]], bridge: tuple[str, str]) -> tuple[set[str], set[str]]:
    """The scans on either side of ``bridge`` (``edges`` without it, from each of its ends)."""
    rest = [e for e in edges if e != bridge]
    adj = _adjacency(rest)
    out = []
    for end in bridge:
        seen, todo = {end}, [end]
        while todo:
            for nxt, _ in adj.get(todo.pop(), []):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        out.append(seen)
    return out[0], out[1]


def bridge_sides(edges: list[tuple[str, str]]) -> list[tuple[set[str], set[str]]]:
    """For each bridge of ``edges`` (:func:`bridges`, in order) its two :func:`sides`, the
    smaller first (a tie: the side of the bridge's first scan)."""
    out = []
    for bridge in bridges(edges):
        a, b = sides(edges, bridge)
        out.append((a, b) if len(a) <= len(b) else (b, a))
    return out


def crosses(pair: tuple[str, str], small: set[str], large: set[str]) -> bool:
    """Whether ``pair`` joins a scan of ``small`` to one of ``large`` (closes a loop over the
    bridge between them)."""
    u, v = pair
    return (u in small and v in large) or (u in large and v in small)
