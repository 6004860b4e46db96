"""closure_confirmation: Karto's chain rule kept per submap, on the nodes' local poses it is handed."""
import numpy as np

from carto_cli.mapping.closure_confirmation import CONFIRM_NEIGHBOURS, ClosureConfirmation
from carto_cli.mapping.constraint_builder import LoopClosure

# Ten nodes of trajectory 0 along x, 0.5 m apart, then two of trajectory 1.
LOCAL = np.array([[0.5 * i, 0.0, 0.0] for i in range(10)] + [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
TRAJECTORIES = [0] * 10 + [1, 1]


def _closure(node, x, y=0.0, submap=0):
    return LoopClosure(node, submap, np.array([x, y, 0.0]), 0.6, False)


def test_a_closure_waits_until_a_neighbours_closure_agrees_with_local_slam():
    c = ClosureConfirmation()
    first = _closure(9, 4.5)
    assert c.agreeing(first, LOCAL, TRAJECTORIES) == [] and c.keep(first, []) == []
    assert c.unconfirmed == 1
    off = _closure(7, 3.5, 1.0)  # 1 m off what local SLAM says between nodes 7 and 9
    assert c.agreeing(off, LOCAL, TRAJECTORIES) == []
    c.keep(off, [])
    agreeing_one = _closure(8, 4.0)
    agreeing = c.agreeing(agreeing_one, LOCAL, TRAJECTORIES)
    assert [e.node for e in agreeing] == [9]
    newly = c.keep(agreeing_one, agreeing)
    assert [e.node for e in newly] == [9] and newly[0].inserted
    assert c.unconfirmed == 1  # node 7's still waits
    # Already inserted: a later agreeing closure does not insert node 9's again.
    again = _closure(8, 4.0)
    assert [e.node for e in c.keep(again, c.agreeing(again, LOCAL, TRAJECTORIES))] == []


def test_closures_of_other_trajectories_or_submaps_never_agree():
    c = ClosureConfirmation()
    c.keep(_closure(1, 0.5), [])
    assert c.agreeing(_closure(11, 0.5), LOCAL, TRAJECTORIES) == []  # trajectory 1
    assert c.agreeing(_closure(2, 1.0, submap=1), LOCAL, TRAJECTORIES) == []  # another submap
    assert [e.node for e in c.agreeing(_closure(2, 1.0), LOCAL, TRAJECTORIES)] == [1]


def test_neighbours_are_the_nearest_searchable_nodes_of_the_trajectory():
    c = ClosureConfirmation()
    points = [np.zeros((5, 2))] * 12
    points[6] = np.zeros((0, 2))  # an empty scan cannot be matched
    c.keep(_closure(4, 2.0), [])  # already has a closure to submap 0
    assert CONFIRM_NEIGHBOURS == 2 and c.neighbours(5, 0, [3], TRAJECTORIES, points) == [7, 2]
    assert c.neighbours(9, 0, [], TRAJECTORIES, points) == [8, 7]  # never trajectory 1's nodes 10 and 11
