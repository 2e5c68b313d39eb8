"""Routes over the road network: shortest paths by length and the commands they imply."""

from __future__ import annotations

import heapq
import math

import numpy as np

from towndrive.sim.town import Command, Edge, Town


def edge_length(town: Town, edge: Edge) -> float:
    return float(town.network.graph[edge[0]][edge[1]][0].length)


def shortest_route(town: Town, start: Edge, goal: Edge) -> list[Edge]:
    """Edges from ``start`` to ``goal`` (both included), shortest by lane length (Dijkstra)."""
    graph = town.network.graph
    best = {start[1]: 0.0}
    parent: dict[str, str] = {}
    heap = [(0.0, start[1])]
    while heap:
        cost, node = heapq.heappop(heap)
        if node == goal[0]:
            break
        if cost > best.get(node, math.inf):
            continue
        for nxt, lanes in graph.get(node, {}).items():
            c = cost + float(lanes[0].length)
            if c < best.get(nxt, math.inf):
                best[nxt] = c
                parent[nxt] = node
                heapq.heappush(heap, (c, nxt))
    if goal[0] != start[1] and goal[0] not in parent:
        raise ValueError(f"No route from {start} to {goal}.")
    nodes = [goal[0]]
    while nodes[-1] != start[1]:
        nodes.append(parent[nodes[-1]])
    nodes.reverse()
    return [start] + [(a, b) for a, b in zip(nodes[:-1], nodes[1:], strict=True)] + [goal]


def random_route(town: Town, start: Edge, rng: np.random.Generator, min_length_m: float = 250.0) -> list[Edge]:
    """A shortest route from ``start`` to a random road at least ``min_length_m`` away."""
    roads = sorted({k[:2] for k in town.road_lanes()})
    for _ in range(200):
        goal = roads[int(rng.integers(len(roads)))]
        if goal == start:
            continue
        route = shortest_route(town, start, goal)
        if route_length(town, route) >= min_length_m:
            return route
    return route


def route_length(town: Town, route: list[Edge]) -> float:
    return sum(edge_length(town, e) for e in route)


def random_next_edge(town: Town, edge: Edge, rng: np.random.Generator) -> Edge:
    """A random continuation of an edge (used to keep NPC routes going forever)."""
    options = sorted(town.network.graph[edge[1]].keys())
    return edge[1], options[int(rng.integers(len(options)))]


def edge_command(town: Town, edge: Edge) -> Command:
    return town.lane_info[(edge[0], edge[1], 0)].command


def command_at(town: Town, route: list[Edge], index: int, s: float, horizon_m: float = 50.0) -> Command:
    """The command a driver is given at route position ``index`` (edge) and ``s`` metres along it.

    Inside a junction it is that junction's turn; on a road it announces the next junction's turn
    once the stop line is within ``horizon_m`` (early enough to change into the lane the turn starts
    from); otherwise it is FOLLOW.
    """
    current = edge_command(town, route[index])
    if town.lane_info[(route[index][0], route[index][1], 0)].kind == "connector":
        return current
    if index + 1 < len(route) and edge_length(town, route[index]) - s <= horizon_m:
        return edge_command(town, route[index + 1])
    return Command.FOLLOW
