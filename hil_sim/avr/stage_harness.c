/* Runs an AVR firmware ELF (the stage board's Marlin) under simavr for the SIL: UART0 on a
 * pseudo-terminal, step/dir pins counted per axis, endstop pins driven from the counted
 * position, simulated time and counts reported on stdout.
 *
 * usage: stage_harness FIRMWARE.elf [--mcu atmega2560] [--freq 16000000] [--speed 1.0] [--lockstep]
 *            [--link PATH] [--axis NAME:STEP:DIR:ENDSTOP:TRIGGER ...]
 *   STEP, DIR, ENDSTOP are pins as port letter + bit (F0, E5); ENDSTOP may be '-'; DIR
 *   written !F1 counts DIR low as positive (Marlin's INVERT_x_DIR).
 *   TRIGGER: the count at or below which the min endstop reads triggered: high, or low if
 *   ENDSTOP is written !E5 (Marlin's x_MIN_ENDSTOP_HIT_STATE LOW).
 * stdout: "pty PATH" once, then "t SECONDS C1 C2 ..." whenever a count changed (at most
 * every 1 ms of simulated time) and at least every 50 ms, and "exit STATE" at the end.
 * stdin: "quit" ends the run.
 *
 * --lockstep (what `dmdsm sim --stage-firmware` uses): no pty and no pacing; the caller owns
 * time. stdin lines: "w HEX" queues bytes for UART0; "r CYCLE" runs until that CPU cycle,
 * then prints "u HEX" (UART0 output, if any), "e AXIS S1 S2 ..." per axis that stepped (each
 * step's cycle + 1, negative for a step down) and "d CYCLE STATE"; "reset" is the DTR reset
 * (counts kept: the carriage does not move) and answers "d CYCLE STATE"; "h CYCLE" ends the
 * bootloader's hold: the clock jumps to CYCLE with nothing run, then the chip starts from
 * reset once; "quit" ends it.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <simavr/avr_extint.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_elf.h>

#include "harness.h"

axis_t axes[MAX_AXES];
int n_axes;
avr_t *avr;
int pty_master = -1;
int uart_xon = 1;
int counts_changed;
volatile sig_atomic_t stop_requested;
static int lockstep;
uint8_t *uart_out;
size_t n_out;
static size_t cap_out;

void *grow(void *buf, size_t *cap, size_t need, size_t size)
{
	if (need <= *cap)
		return buf;
	size_t c = *cap ? *cap : 256;
	while (c < need)
		c *= 2;
	void *b = realloc(buf, c * size);
	if (!b) {
		fprintf(stderr, "stage_harness: out of memory\n");
		exit(2);
	}
	*cap = c;
	return b;
}

static int parse_pin(const char *s, char *port, int *bit)
{
	if (s[0] == '-') {
		*port = 0;
		*bit = -1;
		return 0;
	}
	if (s[0] < 'A' || s[0] > 'L' || s[1] < '0' || s[1] > '7' || s[2] != 0)
		return -1;
	*port = s[0];
	*bit = s[1] - '0';
	return 0;
}

static int parse_axis(char *spec, axis_t *a)
{
	char *f[5];
	int n = 0;
	for (char *tok = strtok(spec, ":"); tok && n < 5; tok = strtok(NULL, ":"))
		f[n++] = tok;
	if (n != 5 || strlen(f[0]) >= sizeof(a->name))
		return -1;
	snprintf(a->name, sizeof(a->name), "%s", f[0]);
	a->dir_inverted = f[2][0] == '!';
	a->end_inverted = f[3][0] == '!';
	if (parse_pin(f[1], &a->step_port, &a->step_bit) || a->step_bit < 0 ||
	    parse_pin(f[2] + a->dir_inverted, &a->dir_port, &a->dir_bit) || a->dir_bit < 0 ||
	    parse_pin(f[3] + a->end_inverted, &a->end_port, &a->end_bit))
		return -1;
	a->trigger = strtol(f[4], NULL, 10);
	return 0;
}

/* the level each port's endstop pins are held at, which a pull-up must not override */
static uint8_t ext_mask['L' - 'A' + 1], ext_value['L' - 'A' + 1];

/* the endstop pin follows the counted position */
static void drive_endstop(axis_t *a)
{
	if (!a->end_irq)
		return;
	int level = (a->count <= a->trigger) != a->end_inverted;
	if (level != a->end_level) {
		int k = a->end_port - 'A';
		a->end_level = level;
		ext_mask[k] |= 1u << a->end_bit;
		ext_value[k] = (ext_value[k] & ~(1u << a->end_bit)) | (level << a->end_bit);
		/* simavr sets an input pin high when the firmware enables its pull-up
		 * (ENDSTOPPULLUPS) unless the pin is marked as driven from outside */
		avr_ioport_external_t ext = {.name = a->end_port, .mask = ext_mask[k],
					     .value = ext_value[k]};
		avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL(a->end_port), &ext);
		avr_raise_irq(a->end_irq, level);
	}
}

static void on_step(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	axis_t *a = param;
	int level = value & 1;
	if (level && !a->step_level) {  /* rising edge: one step (DIR high = positive) */
		int up = a->dir_level != a->dir_inverted;
		a->count += up ? 1 : -1;
		if (lockstep) {
			a->edges = grow(a->edges, &a->cap_edges, a->n_edges + 1, sizeof(long long));
			long long c = (long long)avr->cycle + 1;
			a->edges[a->n_edges++] = up ? c : -c;
		}
		counts_changed = 1;
		drive_endstop(a);
	}
	a->step_level = level;
}

static void on_dir(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	((axis_t *)param)->dir_level = value & 1;
}

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)param;
	uint8_t b = value;
	if (lockstep) {
		uart_out = grow(uart_out, &cap_out, n_out + 1, 1);
		uart_out[n_out++] = b;
		return;
	}
	if (pty_master >= 0 && write(pty_master, &b, 1) < 0 && errno != EAGAIN)
		pty_master = -1;
}

static void on_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	(void)param;
	uart_xon = 1;
}

static void on_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
	(void)irq;
	(void)value;
	(void)param;
	uart_xon = 0;
}

static void on_signal(int sig)
{
	(void)sig;
	stop_requested = 1;
}

/* settings a reset may undo: UART0 neither sleeps on polls nor echoes to stdio, and no
 * strict level interrupts */
void configure(void)
{
	uint32_t flags = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
	flags &= ~(AVR_UART_FLAG_POLL_SLEEP | AVR_UART_FLAG_STDIO);
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
	/* an endstop held low on an INTn pin (the Chiron's Z2 stop, D18/INT3) would re-raise a
	 * low-level interrupt every cycle in simavr's strict mode, slowing the run 4x; the
	 * firmware does not use INTn (Marlin polls endstops without ENDSTOP_INTERRUPTS_FEATURE),
	 * and an edge still raises it once */
	for (uint8_t i = 0; i < 8; i++)
		avr_extint_set_strict_lvl_trig(avr, i, 0);
	for (int i = 0; i < n_axes; i++) {
		axes[i].end_level = -1;
		drive_endstop(&axes[i]);
	}
}

static void wire(void)
{
	configure();
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
				on_uart_out, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
				on_xon, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
				on_xoff, NULL);
	for (int i = 0; i < n_axes; i++) {
		axis_t *a = &axes[i];
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(a->step_port),
						      a->step_bit), on_step, a);
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(a->dir_port),
						      a->dir_bit), on_dir, a);
		if (a->end_bit >= 0) {
			a->end_irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(a->end_port),
						   a->end_bit);
			a->end_level = -1;
			drive_endstop(a);
		}
	}
}

int main(int argc, char **argv)
{
	const char *elf = NULL, *mcu = "atmega2560", *link = NULL;
	unsigned long freq = 16000000;
	double speed = 1.0;
	for (int i = 1; i < argc; i++) {
		if (!strcmp(argv[i], "--mcu") && i + 1 < argc)
			mcu = argv[++i];
		else if (!strcmp(argv[i], "--freq") && i + 1 < argc)
			freq = strtoul(argv[++i], NULL, 10);
		else if (!strcmp(argv[i], "--speed") && i + 1 < argc)
			speed = atof(argv[++i]);
		else if (!strcmp(argv[i], "--lockstep"))
			lockstep = 1;
		else if (!strcmp(argv[i], "--link") && i + 1 < argc)
			link = argv[++i];
		else if (!strcmp(argv[i], "--axis") && i + 1 < argc && n_axes < MAX_AXES) {
			if (parse_axis(argv[++i], &axes[n_axes++])) {
				fprintf(stderr, "stage_harness: bad --axis %s (NAME:STEP:DIR:END:TRIGGER)\n",
					argv[i]);
				return 2;
			}
		} else if (argv[i][0] != '-' && !elf)
			elf = argv[i];
		else {
			fprintf(stderr, "stage_harness: unknown argument %s\n", argv[i]);
			return 2;
		}
	}
	if (!elf) {
		fprintf(stderr, "usage: stage_harness FIRMWARE.elf [--mcu M] [--freq HZ] "
			"[--speed X] [--link PATH] [--lockstep] [--axis NAME:STEP:DIR:END:TRIGGER ...]\n");
		return 2;
	}
	elf_firmware_t fw;
	memset(&fw, 0, sizeof(fw));
	if (elf_read_firmware(elf, &fw) != 0) {
		fprintf(stderr, "stage_harness: cannot read %s as an AVR ELF\n", elf);
		return 2;
	}
	if (!fw.mmcu[0])
		snprintf(fw.mmcu, sizeof(fw.mmcu), "%s", mcu);
	if (!fw.frequency)
		fw.frequency = freq;
	avr = avr_make_mcu_by_name(fw.mmcu);
	if (!avr) {
		fprintf(stderr, "stage_harness: simavr has no MCU %s\n", fw.mmcu);
		return 2;
	}
	avr_init(avr);
	avr->log = LOG_ERROR;  /* simavr's own messages would mix with the report lines */
	avr_load_firmware(avr, &fw);
	signal(SIGINT, on_signal);
	signal(SIGTERM, on_signal);
	wire();  /* before any cycle runs, so no step or byte is missed */
	return lockstep ? run_lockstep() : run_pty(link, speed);
}
