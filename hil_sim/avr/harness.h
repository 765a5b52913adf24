/* What the stage harness's files share: the axes, the simavr core and the UART state. */
#ifndef DMDSM_STAGE_HARNESS_H
#define DMDSM_STAGE_HARNESS_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

#include <simavr/sim_avr.h>

#define MAX_AXES 6

typedef struct axis_t {
	char name[8];
	char step_port, dir_port, end_port;
	int step_bit, dir_bit, end_bit;
	long trigger;
	long count;
	long long *edges;  /* lock-step: this run's steps, signed cycle + 1 */
	size_t n_edges, cap_edges;
	int dir_level, step_level, end_level, dir_inverted, end_inverted;
	avr_irq_t *end_irq;
} axis_t;

extern axis_t axes[MAX_AXES];
extern int n_axes;
extern avr_t *avr;
extern int pty_master;               /* pty mode: the host's side of UART0, or -1 */
extern int uart_xon;                 /* UART0 accepts another byte */
extern int counts_changed;           /* pty mode: a step since the last report */
extern volatile sig_atomic_t stop_requested;
extern uint8_t *uart_out;            /* lock-step: UART0 output since the last run */
extern size_t n_out;

/* buf grown to hold `need` items of `size` bytes (exits on failure) */
void *grow(void *buf, size_t *cap, size_t need, size_t size);
/* settings a reset may undo (UART flags, level interrupts, endstop levels) */
void configure(void);
/* the caller owns time: commands on stdin, results on stdout (stage_harness.c's top) */
int run_lockstep(void);
/* UART0 on a pseudo-terminal, paced to at most `speed` x real time */
int run_pty(const char *link, double speed);

#endif
