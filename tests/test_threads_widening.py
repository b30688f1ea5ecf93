"""`map_threads_widening`: fewer calls at once until another task is done, then all."""

import threading
import time
from concurrent.futures import Future

from cfm_fem.threads import map_threads_widening


def test_calls_run_one_at_a_time_until_the_future_is_done_then_side_by_side():
    widen = Future()
    lock = threading.Lock()
    running, most = [0], []

    def work(x):
        with lock:
            running[0] += 1
            most.append((widen.done(), running[0]))
            second = len(most) == 2
        if second:
            widen.set_result(None)  # the other task ends while the second call runs
        time.sleep(0.05)
        with lock:
            running[0] -= 1
        return 2 * x

    assert map_threads_widening(work, range(6), 1, 3, widen) == [0, 2, 4, 6, 8, 10]
    assert max(n for done, n in most if not done) == 1
    assert max(n for done, n in most if done) >= 2


def test_a_failed_task_widens_too_and_results_keep_their_order():
    widen = Future()
    widen.set_exception(RuntimeError("figures failed"))
    assert map_threads_widening(lambda x: x + 1, [3, 1, 2], 1, 2, widen) == [4, 2, 3]
