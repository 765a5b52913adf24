/* Start-up failures of the NUCLEO board: which step failed, its error log line, and LD3's blink code. */
#include <string.h>

#include "nucleo.h"

/*
 * clock_init and adc_init record each failed step here (they run before the
 * core exists); once the core is up, boot_report sends one error `log` per
 * record and the main loop blinks LD3 with the number of the first failed
 * step (docs/firmware.md has the table).
 */
#define MAX_FAILURES 4u

struct failure {
    enum boot_step step;
    uint8_t code;     /* enum dmdsm_error */
    const char *text; /* a string constant naming the step and what the board does now */
};

static struct {
    unsigned n;
    struct failure f[MAX_FAILURES];
} boot;

void boot_fail(enum boot_step step, uint8_t code, const char *text)
{
    if (boot.n < MAX_FAILURES)
        boot.f[boot.n++] = (struct failure){step, code, text};
}

unsigned boot_failed_step(void)
{
    unsigned first = 0;
    for (unsigned i = 0; i < boot.n; i++)
        if (first == 0 || boot.f[i].step < first)
            first = boot.f[i].step;
    return first;
}

/* the protocol's name of a boot error code, for the board name */
static const char *code_name(uint8_t code)
{
    switch (code) {
    case DMDSM_ERROR_CLOCK_FAILURE:
        return "clock_failure";
    case DMDSM_ERROR_POWER_FAILURE:
        return "power_failure";
    case DMDSM_ERROR_ADC_FAILURE:
        return "adc_failure";
    default:
        return "internal";
    }
}

/* "<base>" or "<base>, boot: clock_failure+adc_failure" into out[cap] */
void boot_board_name(char *out, size_t cap, const char *base)
{
    size_t n = 0;
    out[0] = '\0';
    for (const char *p = base; *p && n + 1 < cap; p++)
        out[n++] = *p;
    for (unsigned i = 0; i < boot.n; i++) {
        const char *sep = i == 0 ? ", boot: " : "+";
        const char *name = code_name(boot.f[i].code);
        if (strstr(out, name) != NULL)
            continue; /* one name per code */
        for (const char *p = sep; *p && n + 1 < cap; p++)
            out[n++] = *p;
        for (const char *p = name; *p && n + 1 < cap; p++)
            out[n++] = *p;
        out[n] = '\0';
    }
    out[n] = '\0';
}

void boot_report(struct dmdsm_core *core)
{
    for (unsigned i = 0; i < boot.n; i++)
        dmdsm_core_log(core, DMDSM_LOG_LEVEL_ERROR, boot.f[i].code, boot.f[i].text);
}

/*
 * LD3 after a failed start-up: N short blinks (200 ms on, 300 ms off), then
 * 1.5 s dark, repeated; N = the first failed step. ms: milliseconds since boot.
 */
bool boot_led(uint64_t ms)
{
    unsigned n = boot_failed_step();
    uint64_t t = ms % (n * 500u + 1500u);
    return n != 0 && t < n * 500u && t % 500u < 200u;
}
